// A part of a page that follows the server: an element with an id and
// data-refresh-s="N" is fetched again every N seconds (the same URL) and its content
// replaced by the fresh page's, so a list of live things never shows a state that
// ended. Times in it are written the page's one way (IoUV.clock).
(() => {
  "use strict";

  async function refresh(node) {
    try {
      const response = await fetch(window.location.href, {
        credentials: "same-origin",
        headers: { Accept: "text/html" },
      });
      if (!response.ok) return;
      const fresh = new DOMParser().parseFromString(await response.text(), "text/html").getElementById(node.id);
      if (!fresh) return;
      node.replaceChildren(...fresh.childNodes);
      for (const time of node.querySelectorAll("time[datetime][data-clock]")) {
        time.textContent = window.IoUV.clock(time.getAttribute("datetime"));
      }
      node.dataset.refreshedAt = new Date().toISOString();
    } catch (e) {
      // Unreachable for now: the next round tries again.
    }
  }

  document.addEventListener("DOMContentLoaded", () => {
    for (const node of document.querySelectorAll("[id][data-refresh-s]")) {
      const seconds = Math.max(1, Number(node.dataset.refreshS) || 5);
      setInterval(() => refresh(node), seconds * 1000);
    }
  });
})();
