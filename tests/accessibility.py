"""Accessibility checks in the browser tests: the vendored axe-core, run in the page.

    from tests.accessibility import axe_violations, violations_report

    found = await axe_violations(page)
    assert not found, violations_report(found)

axe-core (``tests/vendor/axe-core/``, test-only: the platform never serves it) checks
the page as it is when called (what the DOM holds then, with its computed styles), so
call it once the page shows what it is meant to show.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from playwright.async_api import Page

AXE_PATH = Path(__file__).resolve().parent / "vendor" / "axe-core" / "axe.min.js"

#: What axe runs: the WCAG 2.x A and AA rules (the level the portal aims at) and axe's
#: own best practices, which include landmarks, headings and the like.
AXE_TAGS = ["wcag2a", "wcag2aa", "wcag21a", "wcag21aa", "wcag22aa", "best-practice"]

#: Runs axe on the whole document and keeps, of each violation, what a developer needs
#: to find and fix it. The impacts to keep come as the argument.
_RUN = """async ([tags, impacts]) => {
  const results = await window.axe.run(document, {
    runOnly: { type: "tag", values: tags },
    resultTypes: ["violations"],
  });
  return results.violations
    .filter((v) => impacts.includes(v.impact))
    .map((v) => ({
      id: v.id,
      impact: v.impact,
      help: v.help,
      helpUrl: v.helpUrl,
      nodes: v.nodes.map((n) => ({
        target: n.target.map(String),
        html: n.html,
        summary: n.failureSummary,
      })),
    }));
}"""


@functools.cache
def axe_source() -> str:
    """The vendored axe-core's script (read once)."""
    return AXE_PATH.read_text(encoding="utf-8")


async def axe_violations(
    page: Page, impacts: Iterable[str] = ("serious", "critical")
) -> list[dict[str, Any]]:
    """Inject axe into ``page`` and run it; returns the violations of ``impacts``, each
    ``{"id", "impact", "help", "helpUrl", "nodes": [{"target", "html", "summary"}]}``.

    The portal's pages run under a Content-Security-Policy that forbids inline scripts
    and eval, so a ``<script>`` tag (``page.add_script_tag``) would be refused. Playwright's
    ``page.evaluate`` runs the script through the DevTools protocol instead, which the
    page's policy does not govern, and axe itself needs no eval: so axe is checked
    against the page under its real policy, without ``bypass_csp``.
    """
    if not await page.evaluate("() => Boolean(window.axe)"):
        await page.evaluate(axe_source())
    found: list[dict[str, Any]] = await page.evaluate(_RUN, [AXE_TAGS, list(impacts)])
    return found


def violations_report(violations: list[dict[str, Any]], *, where: str = "") -> str:
    """The violations in words, one rule per paragraph with the elements that fail it:
    the message of a failed assertion."""
    lines = [f"{len(violations)} accessibility violation(s){f' on {where}' if where else ''}:"]
    for v in violations:
        lines.append(f"- {v['id']} ({v['impact']}): {v['help']} <{v['helpUrl']}>")
        for node in v["nodes"]:
            lines.append(f"    at {' '.join(node['target'])}: {node['html'][:160]}")
            summary = (node.get("summary") or "").replace("\n", " / ")
            if summary:
                lines.append(f"      {summary[:400]}")
    return "\n".join(lines)
