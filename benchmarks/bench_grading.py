"""Grading a class: SfM lesson submissions on a LocalCluster of 2 worker processes against one at a time.

Issue 20 item 4. ``--count`` submissions of lessons/04-sfm (200 by default), a fixed mix (shuffled
with ``--seed``, the same list in every run):

- correct (30 %): the fixtures ``solution.py``, ``correct_batched.py``, ``correct_cookbook_polar_eigh.py``
  and the solution with its triangulation rounded to float32 (the lesson's declared correct mutant);
- wrong (60 %): every ``wrong_*.py`` fixture (one per mistake of ``lessons/04-sfm/mistakes.py``), the
  lesson's ``starter.py`` (raises NotImplementedError) and two generic mutants of
  :mod:`lab.lessons.mutants` written as source (the sparsity pattern transposed, the poses negated);
- abusive (10 %): the solution with ``jacobian_sparsity`` replaced by an infinite loop (stopped by the
  lesson's 20 s call timeout), a fork bomb (RLIMIT_NPROC), a 4 GiB allocation (RLIMIT_AS) and a read
  of ``/etc/passwd`` (the sandbox), after tests/lessons/test_sandbox_attacks.py and test_abuse.py.

For each database (``--databases``: a SQLite file, and a database on a real PostgreSQL server started
as the tests start it, tests/lessons/postgres_server.py), two runs over the same submissions, each in a
fresh database with the same assignment seed:

1. ``sequential``: the same jobs one at a time in this process, the server's own path without Dask: the
   queue's claim, then :func:`lab.lessons.jobs.run_job` (the grader in the bubblewrap sandbox, the
   conditional write of the result);
2. ``cluster``: :class:`lab.lessons.service.LessonService` with ``GradingCluster(processes=True,
   workers=2)``, the dispatcher claiming as the cluster has room and each job writing its own result.
   Once ``--kill-at`` of the submissions are graded, the worker process grading one of them is killed
   (``os.kill(pid, SIGKILL)``; the Nanny starts a new one): Dask reruns its job on a worker, and the
   database must still hold exactly one result per submission.

Both runs start warm (the grader imported and the lesson loaded in every grading process: what
``vision-lab worker`` does before it joins) and are timed from the first claim to the last result.
Per submission: the time from its claim to its stored result (``finished - started`` in the table).
From the database after each run: ``lost`` (submissions without a result), ``graded_twice`` (more than
one stored result, the table's ``gradings``), ``reclaimed`` (claimed more than once) and the scores,
which must equal the sequential run's submission by submission (``score_mismatches``).

The cores are shared: the load average is recorded at the start and end of each run, and the CPU time
of each run is measured (this process, its workers and their sandboxes, and the PostgreSQL server's
processes, sampled every 0.1 s with psutil: a lower bound, a process's last < 0.1 s before it ends is
missed). ``cpu_s_per_submission`` is the cost of a grading that does not depend on the load.

    python benchmarks/bench_grading.py [--count 200] [--databases sqlite,postgresql] [--threads 1]

The last line is ``RESULT {json}``: ``throughput_ratio`` (cluster / sequential submissions per second,
the lowest over the databases), ``p50_s`` and ``p99_s`` (the cluster's time per submission, the highest
over the databases), ``lost`` and ``graded_twice`` (summed over every run), ``score_mismatches``, and
per database (``databases.<name>``) both runs' figures.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
LESSON = "04-sfm"
FIXTURES = REPO / "tests" / "fixtures" / "submissions" / "sfm"
SPARSITY = "def jacobian_sparsity(camera_indices, point_indices, num_cameras, num_points):\n"
ABUSE = {
    "infinite_loop": "    while True:\n        pass\n",
    "fork_bomb": ("    import os, time\n    for _ in range(64):\n        if os.fork() == 0:\n"
                  "            time.sleep(30)\n            os._exit(0)\n"),
    "huge_memory": "    import numpy as np\n    return np.ones((1 << 32,), dtype=np.uint8)\n",
    "reads_host_files": "    return open('/etc/passwd').read()\n",
}
SHARES = {"correct": 0.3, "abusive": 0.1}  # the rest is wrong


def _wrapped(source: str, step: str, expression: str) -> str:
    """``source`` with ``step``'s result passed through ``expression`` (``{}``: the original result)."""
    return (source + f"\n\n_original_{step} = {step}\n\n\ndef {step}(*args, **kwargs):\n"
            f"    return {expression.format(f'_original_{step}(*args, **kwargs)')}\n")


def submissions_by_kind() -> dict[str, dict[str, str]]:
    """Category -> name -> source of every distinct submission of the mix."""
    solution = (FIXTURES / "solution.py").read_text()
    correct = {name: (FIXTURES / name).read_text()
               for name in ("solution.py", "correct_batched.py", "correct_cookbook_polar_eigh.py")}
    correct["mutant_float32_triangulation"] = _wrapped(
        solution, "triangulate_points_linear", "np.asarray({}, dtype=np.float32).astype(np.float64)")
    wrong = {p.name: p.read_text() for p in sorted(FIXTURES.glob("wrong_*.py"))}
    wrong["starter.py"] = (REPO / "lessons" / LESSON / "starter.py").read_text()
    wrong["mutant_transposed_sparsity"] = _wrapped(solution, "jacobian_sparsity", "np.asarray({}).T")
    wrong["mutant_negated_poses"] = _wrapped(solution, "estimate_poses_linear", "-np.asarray({})")
    abusive = {name: solution.replace(SPARSITY, SPARSITY + body, 1) for name, body in ABUSE.items()}
    assert all(SPARSITY + body in text for body, text in zip(ABUSE.values(), abusive.values(), strict=True))
    return {"correct": correct, "wrong": wrong, "abusive": abusive}


def mix(count: int, seed: int) -> list[tuple[str, str, str]]:
    """``count`` (category, name, source), each category's share taken in turn from its submissions."""
    kinds = submissions_by_kind()
    counts = {category: round(count * share) for category, share in SHARES.items()}
    counts["wrong"] = count - sum(counts.values())
    chosen = []
    for category, number in counts.items():
        names = list(kinds[category])
        chosen += [(category, names[i % len(names)], kinds[category][names[i % len(names)]])
                   for i in range(number)]
    random.Random(seed).shuffle(chosen)
    return chosen


class CpuClock:
    """CPU seconds used by a set of process trees between :meth:`start` and :meth:`stop` (psutil samples)."""

    def __init__(self, roots: list[int], interval_s: float = 0.1) -> None:
        self.roots = roots
        self.interval_s = interval_s
        self._seen: dict[tuple[int, float], float] = {}
        self._base: dict[tuple[int, float], float] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _sample(self) -> dict[tuple[int, float], float]:
        import psutil

        found = {}
        for pid in self.roots:
            try:
                root = psutil.Process(pid)
                processes = [root, *root.children(recursive=True)]
            except psutil.Error:
                continue
            for process in processes:
                try:
                    with process.oneshot():
                        times = process.cpu_times()
                        found[(process.pid, process.create_time())] = times.user + times.system
                except psutil.Error:
                    continue
        return found

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            for key, value in self._sample().items():
                self._seen[key] = max(value, self._seen.get(key, 0.0))

    def start(self) -> None:
        self._base = self._sample()
        self._seen = dict(self._base)
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name="cpu-clock", daemon=True)
        self._thread.start()

    def stop(self) -> float:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        for key, value in self._sample().items():
            self._seen[key] = max(value, self._seen.get(key, 0.0))
        return sum(value - self._base.get(key, 0.0) for key, value in self._seen.items())


@dataclass(frozen=True)
class Database:
    """Where a run's submissions go: a fresh database for each run."""

    name: str
    folder: Path
    postgres_base: str | None = None

    def fresh(self, label: str) -> str:
        if self.postgres_base is None:
            return f"sqlite:///{self.folder / f'{label}.sqlite'}"
        from postgres_server import new_database

        return new_database(self.postgres_base)

    def server_pids(self) -> list[int]:
        """The PostgreSQL server's postmaster (its backends are its children): its CPU is the run's too."""
        if self.postgres_base is None:
            return []
        import psutil

        port = self.postgres_base.rsplit(":", 1)[1]
        found = []
        for process in psutil.process_iter(["name", "cmdline"]):
            command = process.info["cmdline"] or []
            if process.info["name"] == "postgres" and "-p" in command and port in command:
                found.append(process.pid)
        return found


def submit_all(queue: Any, chosen: list[tuple[str, str, str]], seed: int) -> list[str]:
    queue.set_assignment_seed(LESSON, seed)
    ids = []
    for index, (category, name, source) in enumerate(chosen):
        ids.append(queue.submit(LESSON, "submission.py", source, student=f"{index:04d}-{category}-{name}"))
        time.sleep(0.001)  # claimed in this order (by creation time)
    return ids


def table_figures(queue: Any, ids: list[str], wall_s: float, cpu_s: float, load: tuple[float, float]
                  ) -> dict[str, Any]:
    """A run's figures from what the database holds."""
    import numpy as np

    rows = [queue.get(i) for i in ids]
    times = np.array([r.finished - r.started for r in rows
                      if r.finished is not None and r.started is not None])
    return {
        "submissions": len(ids), "wall_s": wall_s, "per_second": len(ids) / wall_s,
        "p50_s": float(np.percentile(times, 50)) if times.size else None,
        "p99_s": float(np.percentile(times, 99)) if times.size else None,
        "max_s": float(times.max()) if times.size else None,
        "cpu_s": cpu_s, "cpu_s_per_submission": cpu_s / len(ids), "cores_used": cpu_s / wall_s,
        "lost": sum(r.results is None for r in rows),
        "errors": sum(r.status == "error" for r in rows),
        "graded_twice": sum(r.gradings > 1 for r in rows),
        "reclaimed": sum(r.attempts > 1 for r in rows),
        "load_start": load[0], "load_end": load[1],
        "scores": [r.score for r in rows],
    }


def warm_up() -> str:
    """What a grading process loads before its first job (as ``vision-lab worker`` does): the grader and
    the lesson. Returns this process's id, for the log."""
    import importlib

    from lab.lessons.jobs import catalog_for

    importlib.import_module("lab.lessons.grader")
    catalog_for(str(REPO / "lessons")).get(LESSON)
    return str(os.getpid())


def run_sequential(database: Database, chosen: list[tuple[str, str, str]], seed: int) -> dict[str, Any]:
    """The jobs one at a time in this process: claim, then the job as a worker runs it (no Dask)."""
    from lab.lessons.format import LessonCatalog
    from lab.lessons.jobs import register, run_job
    from lab.lessons.service import LessonService
    from lab.lessons.store import SubmissionQueue

    queue = SubmissionQueue(database.fresh("sequential"))
    service = LessonService(catalog=LessonCatalog(REPO / "lessons"), queue=queue)  # for job_of and deadline_s
    register(queue, service.catalog)
    ids = submit_all(queue, chosen, seed)
    warm_up()
    clock = CpuClock([os.getpid(), *database.server_pids()])
    load_start = os.getloadavg()[0]
    clock.start()
    started = time.perf_counter()
    while (claimed := queue.claim(deadline_s=service.deadline_s)) is not None:
        outcome = run_job(service.job_of(claimed))
        if not outcome.stored:
            print(f"  sequential: submission {claimed.id} not stored ({outcome.status})", flush=True)
    wall = time.perf_counter() - started
    figures = table_figures(queue, ids, wall, clock.stop(), (load_start, os.getloadavg()[0]))
    queue.close()
    return figures


def _worker_pids(client: Any) -> dict[str, int]:
    """Dask worker name -> its process id (the table's ``worker`` column holds the name)."""
    pids = client.run(os.getpid)  # address -> pid
    workers = client.scheduler_info()["workers"]
    return {str(info["name"]): int(pids[address]) for address, info in workers.items() if address in pids}


def run_cluster(database: Database, chosen: list[tuple[str, str, str]], seed: int, *, workers: int,
                kill_at: float) -> dict[str, Any]:
    """The same jobs on ``LessonService`` with an embedded cluster of worker processes; one worker killed."""
    from lab.lessons.cluster import GradingCluster
    from lab.lessons.format import LessonCatalog
    from lab.lessons.service import LessonService
    from lab.lessons.store import SubmissionQueue

    queue = SubmissionQueue(database.fresh("cluster"))
    cluster = GradingCluster(workers=workers, processes=True)
    service = LessonService(catalog=LessonCatalog(REPO / "lessons"), queue=queue, cluster=cluster)
    ids = submit_all(queue, chosen, seed)
    cluster.start()
    try:
        cluster.client.wait_for_workers(workers, timeout=120)
        cluster.client.run(warm_up)
        clock = CpuClock([os.getpid(), *database.server_pids()])
        load_start = os.getloadavg()[0]
        clock.start()
        started = time.perf_counter()
        service.start()
        killed: dict[str, Any] = {}
        while True:
            counts = queue.counts(LESSON)
            graded = counts["done"] + counts["error"]
            if graded == len(ids):
                break
            if not killed and kill_at < 1 and graded >= kill_at * len(ids):
                killed = kill_a_worker(cluster.client, queue, ids)
            time.sleep(0.05)
        wall = time.perf_counter() - started
        figures = table_figures(queue, ids, wall, clock.stop(), (load_start, os.getloadavg()[0]))
    finally:
        service.stop()
    if killed:
        row = queue.get(killed["submission"])
        killed.update(status=row.status, gradings=row.gradings, attempts=row.attempts, graded_by=row.worker)
    figures["killed"] = killed or None
    queue.close()
    return figures


def kill_a_worker(client: Any, queue: Any, ids: list[str]) -> dict[str, Any]:
    """SIGKILL the worker process grading a submission now (one that has started); what was killed."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        pids = _worker_pids(client)
        for submission_id in ids:
            row = queue.get(submission_id)
            if row.status == "running" and row.worker in pids:
                os.kill(pids[row.worker], signal.SIGKILL)
                print(f"  killed worker {row.worker} (pid {pids[row.worker]}) grading {row.student}",
                      flush=True)
                return {"submission": submission_id, "student": row.student, "worker": row.worker,
                        "pid": pids[row.worker], "at_s": time.time() - (row.started or time.time())}
        time.sleep(0.05)
    raise RuntimeError("no submission was running on a worker for 60 s: nothing to kill")


def check_databases(names: list[str]) -> None:
    """Refuse an unknown name, or PostgreSQL where its server binaries are missing, before anything runs."""
    for name in names:
        if name not in ("sqlite", "postgresql"):
            raise SystemExit(f"--databases: unknown database {name!r} (sqlite, postgresql)")
    if "postgresql" in names:
        sys.path.insert(0, str(REPO / "tests" / "lessons"))
        from postgres_server import binaries

        if binaries() is None:
            raise SystemExit("PostgreSQL is not installed (apt-get install -y postgresql); "
                             "run with --databases sqlite")


def database_of(name: str, folder: Path) -> Database:
    """SQLite files in ``folder``, or databases on the tests' PostgreSQL server (started on first use, stopped
    when this process exits)."""
    if name == "sqlite":
        return Database("sqlite", folder)
    from postgres_server import start

    return Database("postgresql", folder, postgres_base=start())


def summary(per_database: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The RESULT: each database's two runs and the worst figures over them."""
    out: dict[str, Any] = {"databases": {}}
    for name, runs in per_database.items():
        sequential, cluster = runs["sequential"], runs["cluster"]
        mismatches = sum(a != b for a, b in zip(sequential.pop("scores"), cluster.pop("scores"), strict=True))
        out["databases"][name] = {
            "throughput_ratio": cluster["per_second"] / sequential["per_second"],
            "cpu_ratio": sequential["cpu_s_per_submission"] / cluster["cpu_s_per_submission"],
            "score_mismatches": mismatches, "sequential": sequential, "cluster": cluster}
    runs = list(out["databases"].values())
    every = [run[mode] for run in runs for mode in ("sequential", "cluster")]
    out.update(throughput_ratio=min(r["throughput_ratio"] for r in runs),
               p50_s=max(r["cluster"]["p50_s"] for r in runs), p99_s=max(r["cluster"]["p99_s"] for r in runs),
               sequential_p50_s=max(r["sequential"]["p50_s"] for r in runs),
               lost=sum(r["lost"] for r in every), graded_twice=sum(r["graded_twice"] for r in every),
               reclaimed=sum(r["reclaimed"] for r in every),
               score_mismatches=sum(r["score_mismatches"] for r in runs),
               cpu_s_per_submission=max(r["cluster"]["cpu_s_per_submission"] for r in runs),
               killed_and_recovered=all((r["cluster"]["killed"] or {}).get("gradings") == 1 for r in runs))
    return out


def rounded(value: Any) -> Any:
    if isinstance(value, float):
        return round(value, 3)
    if isinstance(value, dict):
        return {k: rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [rounded(v) for v in value]
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=200, help="submissions per run (default 200)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes of the cluster (default 2)")
    parser.add_argument("--databases", default="sqlite,postgresql",
                        help="comma-separated: sqlite, postgresql (default both)")
    parser.add_argument("--kill-at", type=float, default=0.4,
                        help="kill a worker once this fraction is graded (1: no kill)")
    parser.add_argument("--threads", type=int, default=1, help="math-library threads of each grading process")
    parser.add_argument("--seed", type=int, default=20240917, help="the mix's order and the assignment seed")
    args = parser.parse_args()
    if args.count < 1:
        parser.error("--count must be at least 1")
    for variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
                     "NUMBA_NUM_THREADS"):
        os.environ[variable] = str(args.threads)  # before numpy is imported here or in a worker
    names = args.databases.split(",")
    check_databases(names)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # so the PostgreSQL server stops too (atexit)
    chosen = mix(args.count, args.seed)
    categories = {c: sum(1 for k, _, _ in chosen if k == c) for c in ("correct", "wrong", "abusive")}
    print(f"{args.count} submissions of {LESSON}: {categories}; load {os.getloadavg()[0]:.2f}", flush=True)
    per_database: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="bench-grading-") as scratch:
        for name in names:
            database = database_of(name, Path(scratch))
            runs = {}
            for mode in ("sequential", "cluster"):
                print(f"{database.name} {mode}: grading {args.count} ...", flush=True)
                runs[mode] = (run_sequential(database, chosen, args.seed) if mode == "sequential" else
                              run_cluster(database, chosen, args.seed, workers=args.workers,
                                          kill_at=args.kill_at))
                r = runs[mode]
                print(f"  {r['wall_s']:.1f} s, {r['per_second']:.3f}/s, p50 {r['p50_s']:.2f} s, p99 "
                      f"{r['p99_s']:.2f} s, CPU {r['cpu_s_per_submission']:.2f} s/submission "
                      f"({r['cores_used']:.2f} cores), lost {r['lost']}, graded twice {r['graded_twice']}, "
                      f"load {r['load_start']:.2f} -> {r['load_end']:.2f}", flush=True)
                print("RUN " + json.dumps(rounded({"database": name, "mode": mode, **r})), flush=True)
            per_database[database.name] = runs
    result = summary(per_database)
    result.update(count=args.count, workers=args.workers, threads=args.threads, mix=categories,
                  cores=os.cpu_count(), load_average=os.getloadavg()[0])
    print("RESULT " + json.dumps(rounded(result)))


if __name__ == "__main__":
    main()
