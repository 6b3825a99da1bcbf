"""A network lab for integration tests: sites behind real NAT routers on one machine.

WebRTC between a vehicle and a user only means something across the networks it meets
in the field: home and mobile routers that translate addresses, some of them in the way
hole punching cannot get through (symmetric NAT), some that drop the TURN server. This
module builds those networks out of Linux network namespaces, veth pairs and iptables,
so that real processes (aiortc peers, the agent, Chromium) can be run behind them.

Topology (one lab)::

    root namespace = "the internet"
      bridge <tag>b, 203.0.113.1/26  (coturn, later the platform, listen here; Postgres
      |                               and Redis stay on the root's 127.0.0.1)
      +-- veth <tag>w1 ---- wan 203.0.113.2  [router ns <tag>-vehicle-gw]  NAT
      |                     lan 10.77.1.1 ---- eth0 10.77.1.2  [site ns <tag>-vehicle]
      +-- veth <tag>w2 ---- wan 203.0.113.3  [router ns <tag>-user-gw]     NAT
                            lan 10.77.2.1 ---- eth0 10.77.2.2  [site ns <tag>-user]

A lab may also have **machines** (``NetLab(machines=["a", "b"])``): namespaces on the
bridge itself, with a public address of their own (the subnet's 21st, 22nd, ...) and no
NAT, reachable from the root namespace as the platform's servers are from its nginx::

      +-- veth <tag>m1 ---- eth0 203.0.113.21  [machine ns <tag>-a]
      +-- veth <tag>m2 ---- eth0 203.0.113.22  [machine ns <tag>-b]

``link_down("a")`` cuts a machine off as it cuts a site's uplink.

The root namespace plays the internet because the services the platform needs listen on
its loopback; it does not forward anything (all public hosts share one bridge), so its
``ip_forward`` is left alone. Routers have no default route: a site reaches the public
subnet and nothing else, so no test traffic can leak to a real network.

NAT modes of a router (``iptables -t nat -A POSTROUTING -o wan -j MASQUERADE``):

``"eim"``
    Linux's plain MASQUERADE keeps the source port when it can: endpoint-independent
    mapping, address-and-port-dependent filtering (a "port-restricted cone" NAT). STUN
    hole punching works through it.
``"symmetric"``
    ``--random-fully`` picks a fresh random port for every new flow, so the mapping the
    STUN server saw is useless to the other peer: only TURN gets through.

Either router also drops unsolicited inbound packets in its INPUT chain, as a home router
does. That is not only realism: a probe that reached the router's stack would leave a
conntrack entry behind, and Linux would then move the next outbound flow with the same
ports to another port, which breaks hole punching through an "eim" router by accident.

Every name carries a tag ``nl<pid>x<n>`` (pid of the creating process, counter), short
enough for the 15-character interface-name limit, so that parallel runs never collide
and what a dead run left behind is recognised (and removed) by the next one. The public
subnet is the first /26 of the documentation ranges (203.0.113.0/24, 198.51.100.0/24,
192.0.2.0/24, RFC 5737) that no address or route of the root namespace overlaps, so
several labs can run at once (8 on a machine whose own network is 192.0.2.0/24); the
sites use 10.77.<k>.0/24 inside their own namespaces.

Use::

    ensure_packages("iptables", "coturn")
    with NetLab(nat={"vehicle": "eim", "user": "symmetric"}) as lab:
        with lab.coturn(secret="s3cret") as turn:
            proc = lab.popen("vehicle", [sys.executable, "-m", "tests.netlab_peer", ...])

Processes the lab starts (``popen``, ``coturn``) are killed when it closes, and also when
the process that started them dies (``PR_SET_PDEATHSIG``, set by setpriv: see
``benchmarks.turn_server.DIE_WITH_PARENT``): start them from the thread that
owns the lab, since the signal follows the *thread* that forked them.

Everything here needs root (namespaces, iptables); ``netlab_available()`` says whether it
can run, with the reason when not.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import fcntl
import functools
import ipaddress
import itertools
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import pytest

from benchmarks.delay_proxy import DelayProxy
from benchmarks.turn_server import DIE_WITH_PARENT, TurnServer, TurnServerError, turn_server

NatMode = Literal["eim", "symmetric"]
NAT_MODES: tuple[NatMode, ...] = ("eim", "symmetric")


def nat(vehicle: NatMode, user: NatMode) -> Any:
    """For a test: parametrizes its ``lab`` fixture (tests/integration/conftest.py) with
    the NAT modes of the two sites, the vehicle's and the user's."""
    return pytest.mark.parametrize(
        "lab", [{"vehicle": vehicle, "user": user}], indirect=True, ids=[f"{vehicle}-{user}"]
    )


#: Public subnets a lab may take, in order of preference: the /26s of the RFC 5737
#: documentation ranges (a lab needs 1 + number of sites addresses).
PUBLIC_SUBNETS: tuple[ipaddress.IPv4Network, ...] = tuple(
    subnet
    for block in ("203.0.113.0/24", "198.51.100.0/24", "192.0.2.0/24")
    for subnet in ipaddress.IPv4Network(block).subnets(new_prefix=26)
)
#: Site k (1-based, in the order of ``nat``) gets 10.77.k.0/24.
SITE_PREFIX = "10.77"

_TAG_PREFIX = "nl"
_TAG_RE = re.compile(rf"{_TAG_PREFIX}(\d+)x(\d+)")
_counter = itertools.count(1)
_STATE_DIR = Path(tempfile.gettempdir()) / "netlab"
_LOCK_PATH = Path(tempfile.gettempdir()) / "netlab.lock"
#: Debian package -> a binary that proves it is installed.
_PACKAGE_BINARIES = {"iptables": "iptables", "coturn": "turnserver", "iproute2": "ip"}
_SITE_NAME_RE = re.compile(r"[a-z][a-z0-9]{0,15}")


class NetLabError(RuntimeError):
    """A command that builds or changes the lab failed (the message has its stderr)."""


# -- helpers -----------------------------------------------------------------------------


def _run(argv: Sequence[str], *, check: bool = True, input: str | None = None) -> str:
    """Run a short command; its stdout. Raises NetLabError with stderr when it fails."""
    proc = subprocess.run(
        list(argv), input=input, capture_output=True, text=True, check=False, timeout=60
    )
    if check and proc.returncode != 0:
        raise NetLabError(f"{' '.join(argv)} -> {proc.returncode}: {proc.stderr.strip()}")
    return proc.stdout


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _tag_alive(tag: str) -> bool:
    match = _TAG_RE.fullmatch(tag)
    return bool(match) and _pid_alive(int(match.group(1)))


def _stop_process(proc: subprocess.Popen[Any], timeout: float = 5.0) -> None:
    """SIGTERM, then SIGKILL after ``timeout``; reaps it."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@contextlib.contextmanager
def _global_lock() -> Iterator[None]:
    """Serialises lab set-up, clean-up of dead runs and package installs between
    processes (two labs must not pick the same public subnet)."""
    with open(_LOCK_PATH, "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _disable_ipv6(ifname: str) -> None:
    """No IPv6 on a root-side interface of the lab: no link-local chatter, no v6 ICE
    candidates. The setting goes away with the interface."""
    with contextlib.suppress(OSError):
        Path(f"/proc/sys/net/ipv6/conf/{ifname}/disable_ipv6").write_text("1")


# -- availability and packages -----------------------------------------------------------


@functools.cache
def netlab_available() -> tuple[bool, str]:
    """(True, "") when this process can build labs; else (False, why): not Linux, not
    root, no ``ip``, or the kernel refuses network namespaces."""
    if not sys.platform.startswith("linux"):
        return False, "network namespaces need Linux"
    if os.geteuid() != 0:
        return False, "the network lab needs root (network namespaces, iptables)"
    if shutil.which("ip") is None:
        return False, "the network lab needs iproute2's `ip`"
    # Named like a lab (counter 0) so that cleanup_stale() removes it if we die here.
    probe = f"{_TAG_PREFIX}{os.getpid()}x0probe"
    try:
        _run(["ip", "netns", "add", probe])
    except NetLabError as exc:
        return False, f"this kernel/container does not allow network namespaces ({exc})"
    try:
        _run(["ip", "-n", probe, "link", "add", "p0", "type", "veth", "peer", "name", "p1"])
    except NetLabError as exc:
        return False, f"veth pairs are not available ({exc})"
    finally:
        _run(["ip", "netns", "del", probe], check=False)
    return True, ""


def _installed(package: str) -> bool:
    """Whether ``package`` is wholly installed. dpkg's word counts: while another test
    process installs it, its files appear one by one (janus's binary before its
    plugins) and its status is "unpacked" or "half-installed" until the end. A binary
    found without dpkg knowing the package (built by hand) counts too."""
    status = subprocess.run(
        ["dpkg-query", "-W", "-f=${Status}", package], capture_output=True, text=True
    ).stdout.strip()
    if status:
        return status == "install ok installed"
    binary = _PACKAGE_BINARIES.get(package)
    return binary is not None and shutil.which(binary) is not None


def ensure_packages(*packages: str, log_path: Path | None = None) -> None:
    """Install the Debian ``packages`` that are missing (``apt-get install -y``), quietly;
    apt's output goes to ``log_path`` (default: a file in the temp dir), whose tail is in
    the error when it fails. No package starts a system service meanwhile (a temporary
    ``policy-rc.d``), and a coturn service found running afterwards is stopped, so the
    only turnserver processes are the ones the tests start."""
    missing = [p for p in packages if not _installed(p)]
    if not missing:
        return
    if shutil.which("apt-get") is None:
        raise NetLabError(f"no apt-get here: install {' '.join(missing)} by hand")
    if os.geteuid() != 0:
        raise NetLabError(f"must run as root to install {' '.join(missing)}")
    log_path = log_path or Path(tempfile.gettempdir()) / "netlab-apt.log"
    with _global_lock():
        missing = [p for p in missing if not _installed(p)]  # another process may have
        if not missing:
            return
        policy = Path("/usr/sbin/policy-rc.d")
        own_policy = not policy.exists()
        if own_policy:
            # Debian's convention: exit 101 = "no service may be started" (invoke-rc.d,
            # deb-systemd-invoke), which keeps coturn's package from starting its daemon.
            policy.write_text("#!/bin/sh\nexit 101\n")
            policy.chmod(0o755)
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        # Another apt at work (a user's, bin/install-chromium) holds dpkg's lock: wait.
        wait = ["-o", "DPkg::Lock::Timeout=300"]
        install = ["apt-get", *wait, "install", "-y", "-qq", "--no-install-recommends", *missing]
        try:
            with open(log_path, "w") as log:

                def apt(argv: list[str]) -> int:
                    log.write(f"$ {' '.join(argv)}\n")
                    log.flush()
                    return subprocess.run(
                        argv, stdout=log, stderr=subprocess.STDOUT, env=env, check=False
                    ).returncode

                # The package lists may be stale or absent: update only when needed.
                ok = apt(install) == 0 or (
                    apt(["apt-get", *wait, "update", "-qq"]) == 0 and apt(install) == 0
                )
        finally:
            if own_policy:
                policy.unlink(missing_ok=True)
        if not ok:
            tail = "\n".join(log_path.read_text(errors="replace").splitlines()[-20:])
            raise NetLabError(f"apt-get install {' '.join(missing)} failed:\n{tail}")
        if "coturn" in missing:
            _stop_coturn_service()
        still = [p for p in missing if not _installed(p)]
        if still:
            raise NetLabError(f"installed, but still missing: {' '.join(still)}")


def _stop_coturn_service() -> None:
    """Stop the system's coturn service if installing the package started it anyway
    (a pre-existing policy-rc.d that allows starts, or systemd presets)."""
    for pidfile in ("/run/turnserver/turnserver.pid", "/var/run/turnserver.pid"):
        with contextlib.suppress(OSError, ValueError):
            pid = int(Path(pidfile).read_text().split()[0])
            if Path(f"/proc/{pid}/comm").read_text().strip() == "turnserver":
                if Path("/run/systemd/system").exists():
                    _run(["systemctl", "stop", "coturn"], check=False)
                else:
                    _run(["invoke-rc.d", "coturn", "stop"], check=False)
                if _pid_alive(pid):
                    os.kill(pid, signal.SIGTERM)


# -- clean-up of dead runs ---------------------------------------------------------------


def _netns_names() -> list[str]:
    return [line.split()[0] for line in _run(["ip", "netns", "list"]).splitlines() if line]


def _root_links() -> list[str]:
    out = _run(["ip", "-o", "link", "show"])
    # "12: nl123x1w1@if2: <...>" -> "nl123x1w1"
    return [line.split(":")[1].strip().split("@")[0] for line in out.splitlines()]


def _root_firewall_rules() -> list[tuple[str, str]]:
    """(chain, "-A ..." rule) of the root namespace's filter table that a lab inserted
    (they carry the comment ``netlab <tag>``)."""
    if shutil.which("iptables") is None:
        return []
    rules = []
    for chain in ("INPUT", "FORWARD"):
        out = _run(["iptables", "-w", "-S", chain], check=False)
        rules += [(chain, line) for line in out.splitlines() if '"netlab ' in line]
    return rules


def _delete_rule(rule: str) -> None:
    # iptables -S prints "-A CHAIN args..."; the same args after -D delete it.
    args = shlex.split(rule)
    _run(["iptables", "-w", "-D", *args[1:]], check=False)


def _turnserver_processes() -> list[tuple[int, str]]:
    """(pid, tag) of turnserver processes a lab started (its pidfile name has the tag)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        with contextlib.suppress(OSError):
            argv = (entry / "cmdline").read_bytes().split(b"\0")
            if not argv or not argv[0].endswith(b"turnserver"):
                continue
            for arg in argv:
                match = re.search(rb"netlab-turn-(nl\d+x\d+)\.pid$", arg)
                if match:
                    found.append((int(entry.name), match.group(1).decode()))
    return found


def cleanup_stale() -> list[str]:
    """Remove what labs of dead processes left behind (namespaces and the processes in
    them, root-side interfaces, root firewall rules, coturn servers, state dirs); the
    names removed. Labs of live processes (parallel runs) are left alone."""
    removed: list[str] = []
    for pid, tag in _turnserver_processes():
        if not _tag_alive(tag):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
            removed.append(f"turnserver:{pid}")
    for ns in _netns_names():
        match = _TAG_RE.match(ns)
        if match and not _pid_alive(int(match.group(1))):
            for pid_s in _run(["ip", "netns", "pids", ns], check=False).split():
                with contextlib.suppress(ProcessLookupError, ValueError):
                    os.kill(int(pid_s), signal.SIGKILL)
            _run(["ip", "netns", "del", ns], check=False)
            removed.append(f"netns:{ns}")
    for link in _root_links():
        match = _TAG_RE.match(link)
        if match and not _pid_alive(int(match.group(1))):
            _run(["ip", "link", "del", link], check=False)
            removed.append(f"link:{link}")
    for chain, rule in _root_firewall_rules():
        match = _TAG_RE.search(rule)
        if match and not _pid_alive(int(match.group(1))):
            _delete_rule(rule)
            removed.append(f"iptables:{chain}:{match.group(0)}")
    if _STATE_DIR.is_dir():
        for state in _STATE_DIR.iterdir():
            if _TAG_RE.fullmatch(state.name) and not _tag_alive(state.name):
                shutil.rmtree(state, ignore_errors=True)
    return removed


def leftovers(tag: str | None = None) -> list[str]:
    """What still exists of the lab tagged ``tag`` (default: of every lab this process
    made): namespaces, root interfaces, root firewall rules, turnserver processes.
    Empty after clean closes."""

    def ours(name: str) -> bool:
        found = _tag_of(name)
        if found is None:
            return False
        if tag is None:
            return found.startswith(f"{_TAG_PREFIX}{os.getpid()}x")
        return found == tag

    found = [f"netns:{ns}" for ns in _netns_names() if ours(ns)]
    found += [f"link:{link}" for link in _root_links() if ours(link)]
    found += [
        f"iptables:{chain}:{rule}"
        for chain, rule in _root_firewall_rules()
        if (match := _TAG_RE.search(rule)) and ours(match.group(0))
    ]
    found += [f"turnserver:{pid}" for pid, t in _turnserver_processes() if ours(t)]
    return found


def _tag_of(name: str) -> str | None:
    match = _TAG_RE.match(name)
    return match.group(0) if match else None


#: Hosts the machine must still reach while a lab is open: the package registries that
#: tests install from (Debian's, PyPI). A lab's bridge takes the route to its subnet, so
#: a subnet holding one of their addresses would cut the machine off from it: on a
#: sandbox whose registries sit behind a proxy at a documentation address (203.0.113.80
#: here), another test's apt-get would fail while the lab is open.
NEEDED_HOSTS = ("deb.debian.org", "security.debian.org", "pypi.org", "files.pythonhosted.org")


@functools.cache
def _needed_addresses() -> tuple[ipaddress.IPv4Network, ...]:
    """The IPv4 addresses of :data:`NEEDED_HOSTS`, of the hosts apt's sources name and
    of the resolver's name servers, each as a /32 (a name that does not resolve: none)."""
    hosts = set(NEEDED_HOSTS)
    for sources in [Path("/etc/apt/sources.list"), *Path("/etc/apt/sources.list.d").glob("*")]:
        with contextlib.suppress(OSError, UnicodeDecodeError):
            hosts.update(re.findall(r"https?://([^/\s:]+)", sources.read_text()))
    addresses = set()
    for host in hosts:
        with contextlib.suppress(OSError):
            for *_, address in socket.getaddrinfo(host, None, socket.AF_INET):
                addresses.add(str(address[0]))
    with contextlib.suppress(OSError):
        resolver = Path("/etc/resolv.conf").read_text()
        addresses.update(re.findall(r"^nameserver\s+([0-9.]+)\s*$", resolver, re.M))
    return tuple(ipaddress.IPv4Network(a) for a in sorted(addresses))


def _free_public_subnet() -> ipaddress.IPv4Network:
    """The first of PUBLIC_SUBNETS that no IPv4 address or route of the root namespace
    overlaps, nor any address the machine must still reach (:func:`_needed_addresses`)
    (call under _global_lock, until the bridge has its address)."""
    listing = _run(["ip", "-4", "-o", "addr", "show"]) + _run(
        ["ip", "-4", "route", "show", "table", "all"]
    )
    used = list(_needed_addresses())
    for token in listing.split():
        with contextlib.suppress(ValueError):
            used.append(ipaddress.IPv4Network(token, strict=False))
    for subnet in PUBLIC_SUBNETS:
        if not any(subnet.overlaps(net) for net in used if net.prefixlen > 0):
            return subnet
    raise NetLabError(
        "every public test subnet (/26s of 203.0.113.0/24, 198.51.100.0/24, 192.0.2.0/24)"
        " is in use on this machine: too many labs running, or a real network uses them"
    )


# -- the lab -----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Site:
    """One site: a host namespace behind its own NAT router namespace."""

    name: str
    nat: NatMode
    #: Namespace of the site's host (run the peer, agent or browser here).
    netns: str
    #: Namespace of the site's NAT router.
    router_netns: str
    #: The host's address (10.77.k.2) and its gateway, the router's LAN side (10.77.k.1).
    lan_ip: str
    gateway_ip: str
    #: The router's public address on the lab's bridge: what the internet sees.
    wan_ip: str
    #: Root-namespace end of the router's WAN veth (a port of the bridge).
    root_veth: str


@dataclasses.dataclass(frozen=True)
class Machine:
    """One machine: a namespace on the lab's bridge with a public address, no NAT."""

    name: str
    #: Namespace of the machine (run its servers here).
    netns: str
    #: Its address on the bridge, reachable from the root namespace and every site.
    ip: str
    #: Root-namespace end of its veth (a port of the bridge).
    root_veth: str


#: A running coturn of a lab: the benchmarks' own helper, on the lab's public address.
Turn = TurnServer


class NetLab:
    """Sites behind NAT routers, joined by a bridge in the root namespace (see the
    module's docstring). A context manager: built on enter, torn down on exit, also
    after a failure; ``close()`` may be called twice.

    ``nat`` maps site names (lowercase letters and digits) to a NAT mode, in the order
    the sites get 10.77.1.0/24, 10.77.2.0/24, ... (default: a "vehicle" and a "user"
    site, unless the lab has ``machines``); ``machines`` names the machines on the
    bridge. ``workdir`` keeps the logs (coturn's) after the lab closes; by default they
    go to a temp dir deleted on close.
    """

    def __init__(
        self,
        nat: Mapping[str, NatMode] | None = None,
        *,
        machines: Sequence[str] = (),
        workdir: Path | None = None,
    ) -> None:
        if nat is None and not machines:
            nat = {"vehicle": "eim", "user": "eim"}
        self.nat: dict[str, NatMode] = dict(nat or {})
        self.machine_names = list(machines)
        if not len(self.nat) <= 9 or not len(self.machine_names) <= 9:
            raise ValueError("a lab has up to 9 sites and up to 9 machines")
        if not self.nat and not self.machine_names:
            raise ValueError("a lab has a site or a machine")
        names = [*self.nat, *self.machine_names]
        if len(set(names)) != len(names):
            raise ValueError(f"sites and machines need distinct names: {names}")
        for name in self.machine_names:
            if not _SITE_NAME_RE.fullmatch(name):
                raise ValueError(f"machine name {name!r}: lowercase letters and digits, <=16")
        for name, mode in self.nat.items():
            if not _SITE_NAME_RE.fullmatch(name):
                raise ValueError(f"site name {name!r}: lowercase letters and digits, <=16")
            if mode not in NAT_MODES:
                raise ValueError(f"site {name!r}: NAT mode {mode!r} is not one of {NAT_MODES}")
        self.tag = f"{_TAG_PREFIX}{os.getpid()}x{next(_counter) % 1000}"
        self.bridge = f"{self.tag}b"
        self._state_dir = _STATE_DIR / self.tag
        self.workdir = workdir
        self._public: ipaddress.IPv4Network | None = None
        self._sites: dict[str, Site] = {}
        self._machines: dict[str, Machine] = {}
        self._processes: list[subprocess.Popen[Any]] = []
        self._root_rules: list[list[str]] = []
        self._open = False

    # -- public view

    @property
    def public_network(self) -> ipaddress.IPv4Network:
        """The lab's public subnet, e.g. ``203.0.113.0/26`` (set once open)."""
        if self._public is None:
            raise NetLabError("the lab is not open")
        return self._public

    @property
    def public_ip(self) -> str:
        """The root namespace's address on the bridge (the subnet's first address): where
        coturn and the platform listen, reachable from every site through its NAT."""
        return str(self.public_network[1])

    @property
    def sites(self) -> dict[str, Site]:
        return dict(self._sites)

    def site(self, name: str) -> Site:
        return self._sites[name]

    def machine(self, name: str) -> Machine:
        return self._machines[name]

    @property
    def logdir(self) -> Path:
        return self.workdir or self._state_dir

    # -- life cycle

    def __enter__(self) -> NetLab:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        """Build the lab (clean-up of dead runs first). On failure, what was built is
        removed again before the error propagates."""
        if self._open:
            return
        self._open = True
        try:
            with _global_lock():
                cleanup_stale()
                self._state_dir.mkdir(parents=True, exist_ok=True)
                if self.workdir is not None:
                    self.workdir.mkdir(parents=True, exist_ok=True)
                self._public = _free_public_subnet()
                self._build_bridge()
            for index, (name, mode) in enumerate(self.nat.items(), start=1):
                self._build_site(index, name, mode)
            for index, name in enumerate(self.machine_names, start=1):
                self._build_machine(index, name)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Stop the lab's processes, delete its namespaces, interfaces and root firewall
        rules. Errors are collected and raised at the end, after everything was tried."""
        if not self._open:
            return
        self._open = False
        errors: list[str] = []
        for proc in reversed(self._processes):
            try:
                _stop_process(proc)
            except Exception as exc:  # keep tearing down
                errors.append(f"process {proc.pid}: {exc}")
        self._processes.clear()
        for rule in reversed(self._root_rules):
            out = subprocess.run(["iptables", "-w", "-D", *rule], capture_output=True, text=True)
            if out.returncode:
                errors.append(f"iptables -D {' '.join(rule)}: {out.stderr.strip()}")
        self._root_rules.clear()
        # Deleting a namespace deletes the interfaces in it, and with them their veth
        # peers in the root namespace; the bridge goes explicitly.
        for ns in _netns_names():
            if ns.startswith(self.tag + "-"):
                for pid_s in _run(["ip", "netns", "pids", ns], check=False).split():
                    with contextlib.suppress(ProcessLookupError, ValueError):
                        os.kill(int(pid_s), signal.SIGKILL)
                out = subprocess.run(["ip", "netns", "del", ns], capture_output=True, text=True)
                if out.returncode:
                    errors.append(f"ip netns del {ns}: {out.stderr.strip()}")
        for link in _root_links():
            if _tag_of(link) == self.tag:
                subprocess.run(["ip", "link", "del", link], capture_output=True)
        self._sites.clear()
        self._machines.clear()
        # The state dir holds coturn's pidfile and database, and the logs unless a
        # workdir keeps them.
        shutil.rmtree(self._state_dir, ignore_errors=True)
        with _global_lock(), contextlib.suppress(OSError):
            _STATE_DIR.rmdir()  # only when no other lab is using it
        left = leftovers(self.tag)
        if left:
            errors.append(f"left behind: {left}")
        if errors:
            raise NetLabError("network lab teardown: " + "; ".join(errors))

    def leftovers(self) -> list[str]:
        """What of this lab still exists (empty once closed)."""
        return leftovers(self.tag)

    # -- building

    def _build_bridge(self) -> None:
        br = self.bridge
        _run(["ip", "link", "add", br, "type", "bridge", "forward_delay", "0", "stp_state", "0"])
        _disable_ipv6(br)
        _run(["ip", "addr", "add", f"{self.public_ip}/{self.public_network.prefixlen}", "dev", br])
        _run(["ip", "link", "set", br, "up"])
        self._open_root_firewall()

    def _open_root_firewall(self) -> None:
        """Let the lab's traffic through the root namespace's own firewall, if it has
        one: with br_netfilter loaded and ``bridge-nf-call-iptables=1`` (docker sets it)
        frames between the routers go through the root's FORWARD chain, whose policy may
        be DROP; packets to coturn/the platform go through INPUT. The rules are inserted
        first in the chain, name the bridge, carry the lab's tag, and go on close."""
        if shutil.which("iptables") is None:
            return
        bridged = Path("/proc/sys/net/bridge/bridge-nf-call-iptables")
        for chain in ("INPUT", "FORWARD"):
            if chain == "FORWARD" and not (bridged.exists() and bridged.read_text().strip() == "1"):
                continue
            listing = _run(["iptables", "-w", "-S", chain], check=False).splitlines()
            if listing == [f"-P {chain} ACCEPT"]:
                continue  # no firewall in the way: change nothing in the root namespace
            rule = [chain, "-i", self.bridge]
            if chain == "FORWARD":
                rule += ["-o", self.bridge]
            rule += ["-m", "comment", "--comment", f"netlab {self.tag}", "-j", "ACCEPT"]
            _run(["iptables", "-w", "-I", *rule])
            self._root_rules.append(rule)

    def _build_site(self, index: int, name: str, mode: NatMode) -> None:
        router = f"{self.tag}-{name}-gw"
        host = f"{self.tag}-{name}"
        root_veth = f"{self.tag}w{index}"
        wan_ip = str(self.public_network[1 + index])
        lan = f"{SITE_PREFIX}.{index}"
        for ns in (router, host):
            _run(["ip", "netns", "add", ns])
            # IPv4 only: no link-local v6 chatter, no v6 ICE candidates to confuse the
            # candidate-type assertions. Set before the interfaces exist (they inherit).
            self._sysctl(ns, "net.ipv6.conf.all.disable_ipv6", "1")
            self._sysctl(ns, "net.ipv6.conf.default.disable_ipv6", "1")
        self._sysctl(router, "net.ipv4.ip_forward", "1")
        # WAN: veth from the bridge into the router, created with its far end already
        # inside the namespace so no second name is ever taken in the root namespace.
        _run(
            ["ip", "link", "add", root_veth, "type", "veth", "peer", "name", "wan", "netns", router]
        )
        _disable_ipv6(root_veth)
        _run(["ip", "link", "set", root_veth, "master", self.bridge, "up"])
        # LAN: veth between router and host, both ends in their namespaces.
        _run(["ip", "-n", router, *f"link add lan type veth peer name eth0 netns {host}".split()])
        batch_router = [
            "link set lo up",
            f"addr add {wan_ip}/{self.public_network.prefixlen} dev wan",
            "link set wan up",
            f"addr add {lan}.1/24 dev lan",
            "link set lan up",
        ]
        batch_host = [
            "link set lo up",
            f"addr add {lan}.2/24 dev eth0",
            "link set eth0 up",
            f"route add default via {lan}.1",
        ]
        _run(["ip", "-n", router, "-batch", "-"], input="\n".join(batch_router) + "\n")
        _run(["ip", "-n", host, "-batch", "-"], input="\n".join(batch_host) + "\n")
        masquerade = "-A POSTROUTING -o wan -j MASQUERADE" + (
            " --random-fully" if mode == "symmetric" else ""
        )
        rules = f"""*nat
:PREROUTING ACCEPT [0:0]
:INPUT ACCEPT [0:0]
:OUTPUT ACCEPT [0:0]
:POSTROUTING ACCEPT [0:0]
{masquerade}
COMMIT
*filter
:INPUT ACCEPT [0:0]
:FORWARD ACCEPT [0:0]
:OUTPUT ACCEPT [0:0]
-A INPUT -i wan -m conntrack --ctstate ESTABLISHED,RELATED -j ACCEPT
-A INPUT -i wan -j DROP
-A FORWARD -i wan -m conntrack ! --ctstate ESTABLISHED,RELATED -j DROP
COMMIT
"""
        _run(["ip", "netns", "exec", router, "iptables-restore", "-w"], input=rules)
        self._sites[name] = Site(
            name=name,
            nat=mode,
            netns=host,
            router_netns=router,
            lan_ip=f"{lan}.2",
            gateway_ip=f"{lan}.1",
            wan_ip=wan_ip,
            root_veth=root_veth,
        )

    def _build_machine(self, index: int, name: str) -> None:
        ns = f"{self.tag}-{name}"
        root_veth = f"{self.tag}m{index}"
        ip = str(self.public_network[20 + index])
        _run(["ip", "netns", "add", ns])
        self._sysctl(ns, "net.ipv6.conf.all.disable_ipv6", "1")
        self._sysctl(ns, "net.ipv6.conf.default.disable_ipv6", "1")
        _run(["ip", "link", "add", root_veth, "type", "veth", "peer", "name", "eth0", "netns", ns])
        _disable_ipv6(root_veth)
        _run(["ip", "link", "set", root_veth, "master", self.bridge, "up"])
        batch = [
            "link set lo up",
            f"addr add {ip}/{self.public_network.prefixlen} dev eth0",
            "link set eth0 up",
        ]
        _run(["ip", "-n", ns, "-batch", "-"], input="\n".join(batch) + "\n")
        self._machines[name] = Machine(name=name, netns=ns, ip=ip, root_veth=root_veth)

    @staticmethod
    def _sysctl(ns: str, key: str, value: str) -> None:
        _run(["ip", "netns", "exec", ns, "sysctl", "-q", "-w", f"{key}={value}"])

    # -- running things in a site

    def command(self, site: str, argv: Sequence[str], *, router: bool = False) -> list[str]:
        """``argv`` prefixed to run in the site's host (or router) namespace, or in the
        namespace of the machine named ``site``."""
        if site in self._machines:
            return ["ip", "netns", "exec", self._machines[site].netns, *argv]
        s = self._sites[site]
        return ["ip", "netns", "exec", s.router_netns if router else s.netns, *argv]

    def popen(
        self, site: str, argv: Sequence[str], *, router: bool = False, **kwargs: Any
    ) -> subprocess.Popen[Any]:
        """``subprocess.Popen(argv, **kwargs)`` inside the site's host (or router)
        namespace; stopped when the lab closes, or killed when this thread dies."""
        proc: subprocess.Popen[Any] = subprocess.Popen(
            [*DIE_WITH_PARENT, *self.command(site, argv, router=router)], **kwargs
        )
        self._processes.append(proc)
        return proc

    def run(self, site: str, argv: Sequence[str], *, router: bool = False) -> str:
        """Run a short command in the site's host (or router) namespace; its stdout."""
        return _run(self.command(site, argv, router=router))

    # -- faults

    def _block_rule(self, ip: str, port: int | None, proto: str) -> list[str]:
        ipaddress.ip_address(ip)  # a literal address: iptables would resolve a name
        rule = ["FORWARD", "-o", "wan", "-d", ip, "-p", proto]
        if port is not None:
            rule += ["--dport", str(port)]
        return [*rule, "-j", "DROP"]

    def block(self, site: str, ip: str, port: int | None = None, proto: str = "udp") -> None:
        """The site's router drops what the site sends to ``ip`` (``port``, ``proto``):
        e.g. a network that blocks the TURN server. Applies to flows already open too."""
        rule = self._block_rule(ip, port, proto)
        _run(self.command(site, ["iptables", "-w", "-I", *rule], router=True))

    def unblock(self, site: str, ip: str, port: int | None = None, proto: str = "udp") -> None:
        """Undo ``block`` with the same arguments."""
        rule = self._block_rule(ip, port, proto)
        _run(self.command(site, ["iptables", "-w", "-D", *rule], router=True))

    def _root_veth(self, name: str) -> str:
        if name in self._machines:
            return self._machines[name].root_veth
        return self._sites[name].root_veth

    def link_down(self, site: str) -> None:
        """Cut the site's uplink (or the machine named ``site`` off the network): its
        router's WAN loses carrier (the root end of the veth goes down), packets vanish
        silently in both directions as with a pulled cable or a dead radio link;
        addresses, routes, NAT state and open sockets stay."""
        _run(["ip", "link", "set", self._root_veth(site), "down"])

    def link_up(self, site: str) -> None:
        """Restore the site's uplink (the machine's link) after ``link_down``."""
        _run(["ip", "link", "set", self._root_veth(site), "up"])

    # -- the root namespace's services

    @contextlib.contextmanager
    def loopback_offered(self, ports: Sequence[int]) -> Iterator[None]:
        """What listens on the root namespace's 127.0.0.1 at ``ports`` (PostgreSQL,
        Redis) reachable from the lab at ``public_ip`` on the same ports, for the
        machines: a plain TCP forwarder per port (benchmarks.delay_proxy with no delay),
        in a thread and event loop of its own so the test's loop never slows it. A
        machine cut off loses these connections as it loses every other."""
        ready = threading.Event()
        failed: list[BaseException] = []
        loop = asyncio.new_event_loop()
        stop = asyncio.Event()

        async def serve() -> None:
            try:
                async with contextlib.AsyncExitStack() as stack:
                    for port in ports:
                        proxy = DelayProxy(
                            target_port=port, listen_host=self.public_ip, listen_port=port
                        )
                        await stack.enter_async_context(proxy)
                    ready.set()
                    await stop.wait()
            except BaseException as exc:
                failed.append(exc)
                ready.set()

        thread = threading.Thread(
            target=loop.run_until_complete, args=(serve(),), name=f"{self.tag}-forward"
        )
        thread.start()
        try:
            ready.wait()
            if failed:
                raise NetLabError(f"cannot offer {ports} on {self.public_ip}: {failed[0]}")
            yield
        finally:
            loop.call_soon_threadsafe(stop.set)
            thread.join(30)
            loop.close()

    # -- coturn

    @contextlib.contextmanager
    def coturn(
        self,
        secret: str,
        *,
        realm: str = "iouv.test",
        port: int | None = None,
        ready_timeout: float = 10.0,
    ) -> Iterator[Turn]:
        """Run coturn (benchmarks.turn_server) in the root namespace on ``public_ip``
        (STUN + TURN over UDP/TCP on one port, no TLS), with TURN REST credentials
        (``use-auth-secret``, see services.sessions.ice.turn_credentials); yields it once it
        answers a STUN binding request. Relays are allocated on ``public_ip`` and may
        only reach the lab's public subnet. Stopped on exit (and when the lab closes)."""
        if shutil.which("turnserver") is None:
            raise NetLabError('turnserver missing: call ensure_packages("coturn") first')
        # Relay ports: a range of its own per lab (the public address differs per lab
        # anyway); coturn skips ports in use within it.
        relay_min = 50000 + PUBLIC_SUBNETS.index(self.public_network) * 400
        net = self.public_network
        try:
            with turn_server(
                log_dir=self.logdir,
                secret=secret,
                host=self.public_ip,
                port=port,
                realm=realm,
                relay_ports=(relay_min, relay_min + 399),
                peers=f"{net[1]}-{net[-2]}",
                # Named after the lab: cleanup_stale finds a dead run's coturn by it.
                pidfile=self._state_dir / f"netlab-turn-{self.tag}.pid",
                ready_timeout_s=ready_timeout,
            ) as turn:
                self._processes.append(turn.process)
                try:
                    yield turn
                finally:
                    with contextlib.suppress(ValueError):
                        self._processes.remove(turn.process)
        except TurnServerError as exc:
            raise NetLabError(str(exc)) from exc
