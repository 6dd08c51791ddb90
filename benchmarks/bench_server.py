"""Server under load: /api/health and a light step stay fast while heavy steps run and a flood is refused.

Starts the REST API itself (uvicorn on 127.0.0.1, a free port, as a subprocess of this script,
trusting ``X-Forwarded-For`` so each simulated client has an address of its own), then:

1. setup: each light client makes a calibration session (``run-until estimate_homographies``),
   each heavy client a stereo session on the Middlebury motorcycle pair (``rectify_pair``, then one
   heavy step, which also compiles the Numba kernels); the server's resident memory before and
   after gives the memory per session;
2. for ``--duration`` seconds: light clients re-run ``estimate_intrinsics`` (about 1 ms of work)
   with a short think time, heavy clients re-run ``cost_volume`` with NCC over 11 x 11 windows
   (about 1 s on an idle machine), a prober (a process of its own, so the clients' threads do
   not delay it) reads ``/api/health`` every 20 ms, and an attacker floods ``POST /api/sessions``
   (texture sessions, quick to load) over 16 connections: ``--flood`` creations from one address
   (refused past the per-client cap, 429), then as many from as many addresses (refused past the
   total cap, 503); afterwards every client's own session must still be there;
3. the sessions are deleted and the server stopped.

Latencies are wall-clock times of whole HTTP requests over loopback. A refusal is a 429 or 503
(with Retry-After, which the clients honour, at most 1 s); an error is anything else that is not
a success: a 5xx, a lost session (404), a timeout or a broken connection.

    python benchmarks/bench_server.py [--duration 15] [--clients 6] [--heavy-clients 2] [--flood 300]

The last line is ``RESULT {json}``: health_p50_ms, health_p99_ms, light_step_p50_ms,
light_step_p99_ms, heavy_steps, heavy_step_p50_s, memory_per_session_mb, refusals, refused_429,
refused_503, errors, flood_admitted, sessions_lost, duration_s, clients, heavy_clients, workers.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx



@dataclass(frozen=True)
class Workload:
    """A session a client makes (module, dataset options, the step run up to first) and the step it repeats."""

    module: str
    options: dict[str, Any]
    prepare: str
    step: str
    controls: dict[str, Any]
    heavy: bool
    label: str


LIGHT = Workload("calibration", {}, "estimate_homographies", "estimate_intrinsics", {}, False,
                 "calibration estimate_intrinsics")
HEAVY = Workload("stereo", {"downsample": 1}, "rectify_pair", "cost_volume", {"cost": "ncc", "window": 11}, True,
                 "stereo cost_volume (NCC 11 x 11)")
HEALTH_EVERY_S = 0.02
#: /api/health's p99 should stay under this while heavy steps run (a figure to watch, not a test).
HEALTH_TARGET_MS = 100.0
FLOOD_THREADS = 16
#: What the attacker asks for: a session whose dataset loads in milliseconds (texture's default image).
FLOOD_SESSION = {"module": "texture"}
LIGHT_THINK_S = 0.05
#: Longest the server may take to start, and any one request (seconds).
START_TIMEOUT_S = 30.0
REQUEST_TIMEOUT_S = 30.0


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def serve(port: int, workers: int) -> None:
    """The server process: the lab's app with its default caps, trusting X-Forwarded-For."""
    import uvicorn

    from lab.api import create_app
    from lab.core import SessionStore

    app = create_app(SessionStore(), workers=workers, trust_forwarded_for=True)
    uvicorn.run(app, host="127.0.0.1", port=port, log_level="warning")


def rss_mb(pid: int) -> float:
    """Resident memory of a process (MiB), from /proc (Linux)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


@dataclass
class Tally:
    """What the clients saw, shared between their threads."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    health_ms: list[float] = field(default_factory=list)
    light_ms: list[float] = field(default_factory=list)
    heavy_s: list[float] = field(default_factory=list)
    refused: dict[int, int] = field(default_factory=lambda: {429: 0, 503: 0})
    errors: list[str] = field(default_factory=list)

    def outcome(self, response: httpx.Response | None, what: str, error: str = "") -> str:
        """``ok``, ``refused`` (429/503) or ``error``, counted."""
        with self.lock:
            if response is not None and response.is_success:
                return "ok"
            if response is not None and response.status_code in self.refused:
                self.refused[response.status_code] += 1
                return "refused"
            detail = error or (f"{response.status_code} {response.text[:200]}" if response is not None else "?")
            self.errors.append(f"{what}: {detail}")
            return "error"


def request(client: httpx.Client, tally: Tally, what: str, method: str, url: str, **kwargs: Any
            ) -> tuple[str, httpx.Response | None, float]:
    """One request: (outcome, response, seconds)."""
    started = time.perf_counter()
    try:
        response = client.request(method, url, **kwargs)
    except httpx.HTTPError as exc:
        return tally.outcome(None, what, f"{type(exc).__name__}: {exc}"), None, time.perf_counter() - started
    return tally.outcome(response, what), response, time.perf_counter() - started


def backoff(response: httpx.Response | None) -> None:
    """Honour a refusal's Retry-After, at most 1 s (the benchmark is short)."""
    if response is not None:
        time.sleep(min(1.0, float(response.headers.get("Retry-After", "1"))))


def make_session(client: httpx.Client, tally: Tally, work: Workload) -> str | None:
    """A session of ``work``, run up to its prepare step and through its step once; None when refused or failed."""
    outcome, response, _ = request(client, tally, f"create {work.module}", "POST", "/api/sessions",
                                   json={"module": work.module, "options": work.options})
    if outcome != "ok":
        return None
    sid = response.json()["id"]
    prepared, _, _ = request(client, tally, f"{work.module} {work.prepare}", "POST",
                             f"/api/sessions/{sid}/run-until/{work.prepare}")
    ran, _, _ = request(client, tally, work.label, "POST", f"/api/sessions/{sid}/steps/{work.step}",
                        json=work.controls)
    return sid if prepared == ran == "ok" else None


def loop_steps(client: httpx.Client, tally: Tally, sid: str, work: Workload, stop: threading.Event) -> None:
    """Re-run the workload's step until ``stop``, recording successful runs' latencies."""
    while not stop.is_set():
        outcome, response, seconds = request(client, tally, work.label, "POST",
                                             f"/api/sessions/{sid}/steps/{work.step}", json=work.controls)
        if outcome == "ok":
            with tally.lock:
                if work.heavy:
                    tally.heavy_s.append(seconds)
                else:
                    tally.light_ms.append(seconds * 1000)
        elif outcome == "refused":
            backoff(response)
        else:
            time.sleep(0.1)
        if not work.heavy:
            stop.wait(LIGHT_THINK_S)


def probe_health(base: str, duration: float) -> None:
    """The prober process (its own, so the clients' threads do not delay it): GET /api/health every
    HEALTH_EVERY_S for ``duration`` seconds; prints ``{"health_ms": [...], "errors": [...]}``."""
    tally = Tally()
    deadline = time.monotonic() + duration
    with httpx.Client(base_url=base, timeout=REQUEST_TIMEOUT_S) as client:
        while time.monotonic() < deadline:
            outcome, _, seconds = request(client, tally, "health", "GET", "/api/health")
            if outcome == "ok":
                tally.health_ms.append(seconds * 1000)
            time.sleep(HEALTH_EVERY_S)
    print(json.dumps({"health_ms": tally.health_ms, "errors": tally.errors}))


def start_prober(base: str, duration: float) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, __file__, "--probe", base, "--duration", str(duration)],
                            stdout=subprocess.PIPE, text=True)


def prober_figures(prober: subprocess.Popen, tally: Tally) -> None:
    """The prober's latencies and errors, into ``tally``."""
    try:
        out, _ = prober.communicate(timeout=REQUEST_TIMEOUT_S + 10)
        figures = json.loads(out.strip().splitlines()[-1])
    except (subprocess.TimeoutExpired, ValueError, IndexError) as exc:
        prober.kill()
        tally.errors.append(f"health prober: {type(exc).__name__}: {exc}")
        return
    tally.health_ms.extend(figures["health_ms"])
    tally.errors.extend(figures["errors"])


def flood(base: str, tally: Tally, count: int, stop: threading.Event) -> dict[str, Any]:
    """The attacker: ``count`` creations from one address, then ``count`` from as many addresses, each
    phase by FLOOD_THREADS concurrent connections; returns the ids admitted and the statuses seen."""
    admitted: list[str] = []
    by_status: dict[str, dict[int, int]] = {}
    phases = (("one address", lambda i: "10.66.0.1"), ("many addresses", lambda i: f"10.77.{i // 250}.{i % 250 + 1}"))
    for phase, address in phases:
        seen: dict[int, int] = {}
        numbers = iter(range(count))
        lock = threading.Lock()

        def attack() -> None:
            with httpx.Client(base_url=base, timeout=REQUEST_TIMEOUT_S) as client:
                while not stop.is_set():
                    with lock:
                        i = next(numbers, None)
                    if i is None:
                        return
                    outcome, response, _ = request(client, tally, "flood create", "POST", "/api/sessions",
                                                   json=FLOOD_SESSION,
                                                   headers={"X-Forwarded-For": address(i)})
                    with lock:
                        status = response.status_code if response is not None else 0
                        seen[status] = seen.get(status, 0) + 1
                        if outcome == "ok":
                            admitted.append(response.json()["id"])

        threads = [threading.Thread(target=attack) for _ in range(FLOOD_THREADS)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        by_status[phase] = seen
    return {"admitted": admitted, "by_status": by_status}


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(q / 100 * (len(ordered) - 1))))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=15.0, help="seconds of load after setup (default 15)")
    parser.add_argument("--clients", type=int, default=6, help="light-step clients (default 6)")
    parser.add_argument("--heavy-clients", type=int, default=2, help="heavy-step clients (default 2)")
    parser.add_argument("--flood", type=int, default=300, help="session creations per flood phase (default 300)")
    parser.add_argument("--workers", type=int, default=None, help="the server's heavy workers (default: its own)")
    parser.add_argument("--serve", type=int, default=None, help=argparse.SUPPRESS)  # the server subprocess
    parser.add_argument("--probe", default=None, help=argparse.SUPPRESS)  # the health prober subprocess
    args = parser.parse_args()
    if args.serve is not None:
        serve(args.serve, args.workers)
        return
    if args.probe is not None:
        probe_health(args.probe, args.duration)
        return
    if not (1 <= args.duration <= 600 and 0 <= args.clients <= 64 and 0 <= args.heavy_clients <= 16
            and 0 <= args.flood <= 10_000):
        parser.error("--duration must be in [1, 600] s, --clients in [0, 64], --heavy-clients in [0, 16], "
                     "--flood in [0, 10000]")

    from lab.api.runs import DEFAULT_WORKERS

    workers = args.workers or DEFAULT_WORKERS
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = subprocess.Popen([sys.executable, __file__, "--serve", str(port), "--workers", str(workers)],
                              env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        report(args, base, server, workers)
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=10)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


def wait_for_server(base: str, server: subprocess.Popen) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise SystemExit(f"the server exited with code {server.returncode}")
        try:
            if httpx.get(f"{base}/api/health", timeout=1.0).is_success:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise SystemExit(f"the server did not answer within {START_TIMEOUT_S:.0f} s")


def report(args: argparse.Namespace, base: str, server: subprocess.Popen, workers: int) -> None:
    wait_for_server(base, server)
    tally = Tally()
    kinds = [(LIGHT, f"10.1.0.{i + 1}") for i in range(args.clients)]
    kinds += [(HEAVY, f"10.2.0.{i + 1}") for i in range(args.heavy_clients)]
    clients = [httpx.Client(base_url=base, timeout=REQUEST_TIMEOUT_S, headers={"X-Forwarded-For": address})
               for _, address in kinds]

    # Setup: one warm-up session of each kind (imports, Numba kernels), then the measured ones.
    with httpx.Client(base_url=base, timeout=REQUEST_TIMEOUT_S, headers={"X-Forwarded-For": "10.0.0.1"}) as warm:
        for work in [w for w in (LIGHT, HEAVY) if any(k is w for k, _ in kinds)]:
            sid = make_session(warm, tally, work)
            if sid is not None:
                warm.delete(f"/api/sessions/{sid}")
    rss_before = rss_mb(server.pid)
    sessions: list[str | None] = [None] * len(kinds)

    def set_up(i: int) -> None:
        sessions[i] = make_session(clients[i], tally, kinds[i][0])

    threads = [threading.Thread(target=set_up, args=(i,)) for i in range(len(kinds))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    made = [sid for sid in sessions if sid is not None]
    memory_per_session = (rss_mb(server.pid) - rss_before) / max(1, len(made))
    tally.health_ms.clear()  # setup's figures are not the load's
    tally.light_ms.clear()
    tally.heavy_s.clear()

    # Load.
    stop = threading.Event()
    flooded: dict[str, Any] = {}
    workers_threads = []
    for i, sid in enumerate(sessions):
        if sid is not None:
            workers_threads.append(threading.Thread(target=loop_steps,
                                                    args=(clients[i], tally, sid, kinds[i][0], stop)))
    workers_threads.append(threading.Thread(target=lambda: flooded.update(flood(base, tally, args.flood, stop))))
    started = time.perf_counter()
    prober = start_prober(base, args.duration)
    for thread in workers_threads:
        thread.start()
    stop.wait(args.duration)
    stop.set()
    for thread in workers_threads:
        thread.join(timeout=REQUEST_TIMEOUT_S + 5)
    elapsed = time.perf_counter() - started
    prober_figures(prober, tally)

    # Every client's own session must have survived the flood; then clean up.
    lost = 0
    for i, sid in enumerate(sessions):
        if sid is not None:
            if clients[i].get(f"/api/sessions/{sid}").status_code != 200:
                lost += 1
                tally.errors.append(f"session {sid} lost")
            clients[i].delete(f"/api/sessions/{sid}")
    with httpx.Client(base_url=base, timeout=REQUEST_TIMEOUT_S) as cleanup:
        for sid in flooded.get("admitted", []):
            cleanup.delete(f"/api/sessions/{sid}")
    for client in clients:
        client.close()

    result = {
        "health_p50_ms": round(percentile(tally.health_ms, 50), 2),
        "health_p99_ms": round(percentile(tally.health_ms, 99), 2),
        "light_step_p50_ms": round(percentile(tally.light_ms, 50), 2),
        "light_step_p99_ms": round(percentile(tally.light_ms, 99), 2),
        "heavy_steps": len(tally.heavy_s),
        "heavy_step_p50_s": round(percentile(tally.heavy_s, 50), 3),
        "memory_per_session_mb": round(memory_per_session, 1),
        "refusals": sum(tally.refused.values()), "refused_429": tally.refused[429], "refused_503": tally.refused[503],
        "errors": len(tally.errors), "flood_admitted": len(flooded.get("admitted", [])), "sessions_lost": lost,
        "duration_s": round(elapsed, 1), "clients": args.clients, "heavy_clients": args.heavy_clients,
        "workers": workers,
    }
    light, heavy = LIGHT.label, HEAVY.label
    print(f"server {base}, {workers} heavy workers, {os.cpu_count()} CPU(s); {args.clients} light + "
          f"{args.heavy_clients} heavy clients for {elapsed:.1f} s; {len(made)} of {len(kinds)} sessions set up")
    print(f"{'request':<44s} {'count':>6s} {'p50':>10s} {'p99':>10s}")
    print(f"{'GET /api/health':<44s} {len(tally.health_ms):>6d} {result['health_p50_ms']:>7.1f} ms "
          f"{result['health_p99_ms']:>7.1f} ms")
    print(f"{'light step: ' + light:<44s} {len(tally.light_ms):>6d} {result['light_step_p50_ms']:>7.1f} ms "
          f"{result['light_step_p99_ms']:>7.1f} ms")
    print(f"{'heavy step: ' + heavy:<44s} {len(tally.heavy_s):>6d} {result['heavy_step_p50_s']:>8.2f} s")
    print(f"health p99 / the {HEALTH_TARGET_MS:.0f} ms target: {result['health_p99_ms'] / HEALTH_TARGET_MS:.2f}; "
          f"heavy step p50 / health p99: {result['heavy_step_p50_s'] * 1000 / max(result['health_p99_ms'], 1e-9):.0f}")
    for phase, seen in flooded.get("by_status", {}).items():
        print(f"flood from {phase}: " + ", ".join(f"{n} x {status}" for status, n in sorted(seen.items())))
    print(f"memory per session (server RSS): {memory_per_session:.1f} MiB; refusals {result['refusals']} "
          f"(429: {tally.refused[429]}, 503: {tally.refused[503]}); errors {len(tally.errors)}; "
          f"own sessions lost {lost}")
    for error in tally.errors[:5]:
        print(f"  error: {error}")
    print("RESULT " + json.dumps(result))


if __name__ == "__main__":
    main()
