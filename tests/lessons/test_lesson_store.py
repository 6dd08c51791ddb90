"""The persistent submission queue and the grading dispatcher, on SQLite and on a real PostgreSQL server."""

from __future__ import annotations

import threading
import time

import pytest

from lab.lessons.cluster import Dispatcher, GradingCluster
from lab.lessons.jobs import GradingJob, run_job
from lab.lessons.store import MAX_ATTEMPTS, SubmissionQueue
from postgres_server import database_url  # noqa: F401  (a fixture: SQLite, then PostgreSQL)


@pytest.fixture()
def queue(database_url):  # noqa: F811
    q = SubmissionQueue(database_url)
    yield q
    q.close()


def wait_for(predicate, timeout=10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def test_submit_claim_finish(queue):
    first = queue.submit("00-toy", "a.py", "x = 1", student="ana")
    second = queue.submit("00-toy", "b.py", "x = 2")
    assert queue.get(first).status == "queued" and queue.get(first).student == "ana"
    claimed = queue.claim()
    assert claimed.id == first and claimed.status == "running" and claimed.attempts == 1 and claimed.source == "x = 1"
    assert queue.claim().id == second
    assert queue.claim() is None
    queue.finish(first, {"score": 4.0, "tests": [{"max_score": 2.0}, {"max_score": 4.0}]})
    done = queue.get(first)
    assert done.status == "done" and done.score == 4.0 and done.max_score == 6.0 and done.results["score"] == 4.0
    queue.fail(second, "boom")
    assert queue.get(second).status == "error" and queue.get(second).error == "boom"
    assert queue.counts() == {"queued": 0, "running": 0, "done": 1, "error": 1}
    assert queue.get("0" * 32) is None


def test_submissions_survive_a_new_connection(database_url):  # noqa: F811
    submission_id = SubmissionQueue(database_url).submit("00-toy", "a.py", "x = 1")
    assert SubmissionQueue(database_url).get(submission_id).source == "x = 1"


def test_requeue_after_a_crash_and_give_up_after_max_attempts(queue):
    submission_id = queue.submit("00-toy", "a.py", "x = 1")
    for attempt in range(1, MAX_ATTEMPTS + 1):
        assert queue.claim().attempts == attempt
        assert queue.requeue_running() == (1 if attempt < MAX_ATTEMPTS else 0)  # the server "restarts"
    gave_up = queue.get(submission_id)
    assert gave_up.status == "error" and "interrupted" in gave_up.error


def test_each_submission_is_claimed_once_by_concurrent_workers(queue, database_url):  # noqa: F811
    ids = {queue.submit("00-toy", f"{i}.py", "x") for i in range(24)}
    claimed: list[str] = []
    lock = threading.Lock()
    queues = [SubmissionQueue(database_url) for _ in range(4)]  # four writers, four connection pools

    def worker(mine):
        while (job := mine.claim()) is not None:
            with lock:
                claimed.append(job.id)

    threads = [threading.Thread(target=worker, args=(mine,)) for mine in queues]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(claimed) == sorted(ids)


def test_list_by_lesson_newest_first(queue):
    a = queue.submit("00-toy", "a.py", "x")
    time.sleep(0.01)
    b = queue.submit("00-toy", "b.py", "x")
    queue.submit("01-calibration", "c.py", "x")
    assert [s.id for s in queue.list("00-toy")] == [b, a]
    assert "results" not in queue.list("00-toy")[0].to_json(with_results=False)


def test_concurrent_writers_submit_and_finish_without_losing_a_row(queue, database_url):  # noqa: F811
    queues = [SubmissionQueue(database_url) for _ in range(4)]

    def writer(mine, k):
        for i in range(10):
            submission_id = mine.submit("00-toy", f"{k}-{i}.py", "x", student=f"s{k}")
            claimed = mine.claim()
            mine.finish(claimed.id, {"score": 1.0, "tests": []}, attempt=claimed.attempts)
            assert mine.get(submission_id) is not None

    threads = [threading.Thread(target=writer, args=(mine, k)) for k, mine in enumerate(queues)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    rows = queue.list(limit=None)
    assert len(rows) == 40 and all(r.status == "done" and r.gradings == 1 for r in rows)


def test_a_result_is_stored_once_per_claim(queue):
    submission_id = queue.submit("00-toy", "a.py", "x")
    claimed = queue.claim()
    assert queue.mark_started(submission_id, claimed.attempts, "w1")
    assert queue.finish(submission_id, {"score": 3.0, "tests": []}, attempt=claimed.attempts, worker="w2")
    assert not queue.finish(submission_id, {"score": 0.0, "tests": []}, attempt=claimed.attempts)
    assert not queue.fail(submission_id, "late", attempt=claimed.attempts)
    done = queue.get(submission_id)
    assert done.status == "done" and done.score == 3.0 and done.gradings == 1 and done.worker == "w2"


def test_a_stale_claim_cannot_write_after_a_restart(queue):
    submission_id = queue.submit("00-toy", "a.py", "x")
    first = queue.claim()
    queue.requeue_running()  # the server restarted while the first job was still running somewhere
    second = queue.claim()
    assert second.attempts == first.attempts + 1
    assert not queue.mark_started(submission_id, first.attempts, "old")
    assert not queue.finish(submission_id, {"score": 0.0, "tests": []}, attempt=first.attempts)
    assert queue.finish(submission_id, {"score": 2.0, "tests": []}, attempt=second.attempts)
    assert queue.get(submission_id).score == 2.0 and queue.get(submission_id).gradings == 1


def test_a_grading_past_its_deadline_is_marked_failed(queue):
    late = queue.submit("00-toy", "a.py", "x")
    queue.submit("00-toy", "b.py", "x")
    claimed = queue.claim(deadline_s=lambda lesson: 30.0)
    queue.claim(deadline_s=lambda lesson: 3600.0)
    assert queue.fail_overdue(now=time.time() + 10) == []
    assert queue.fail_overdue(now=time.time() + 60) == [(late, claimed.attempts)]
    failed = queue.get(late)
    assert failed.status == "error" and "no result came within 30 s" in failed.error
    assert not queue.finish(late, {"score": 1.0, "tests": []}, attempt=claimed.attempts)  # too late
    assert queue.counts()["running"] == 1


def test_a_job_lost_with_its_scheduler_is_requeued_then_given_up(queue):
    submission_id = queue.submit("00-toy", "a.py", "x")
    for attempt in range(1, MAX_ATTEMPTS + 1):
        claimed = queue.claim()
        assert claimed.attempts == attempt
        assert queue.release(submission_id, attempt)
        assert not queue.release(submission_id, attempt)  # the claim is gone: a second release is void
    gave_up = queue.get(submission_id)
    assert gave_up.status == "error" and "interrupted" in gave_up.error


def test_a_job_run_twice_grades_once(queue):
    submission_id = queue.submit("00-toy", "a.py", "x = 1")
    claimed = queue.claim()
    job = GradingJob(database_url=queue.url, lessons_dir="unused", submission_id=submission_id, lesson="00-toy",
                     attempt=claimed.attempts, seed=7)
    runs = []

    def grade(submission):
        runs.append(submission.id)
        return {"score": float(len(runs)), "tests": []}

    first, second = run_job(job, grade), run_job(job, grade)
    assert (first.status, first.stored) == ("done", True) and (second.status, second.stored) == ("gone", False)
    assert runs == [submission_id]  # the second run saw the claim graded and did not grade again
    assert queue.get(submission_id).score == 1.0 and queue.get(submission_id).gradings == 1


def test_dispatcher_grades_everything_on_the_embedded_cluster_and_records_grader_bugs(queue):
    good = [queue.submit("00-toy", f"{i}.py", "ok") for i in range(3)]
    bad = queue.submit("00-toy", "bug.py", "bug")
    seen = threading.Event()  # not picklable: the embedded cluster keeps an injected function in process

    def grade(job):
        seen.set()
        if job.source == "bug":
            raise RuntimeError("the grader broke")
        return {"score": 1.0, "tests": [{"max_score": 1.0}]}

    def job_of(submission):
        return GradingJob(database_url=queue.url, lessons_dir="unused", submission_id=submission.id,
                          lesson=submission.lesson, attempt=submission.attempts, seed=1)

    dispatcher = Dispatcher(queue, GradingCluster(workers=2), job_of=job_of, grade=grade, poll_s=0.05)
    dispatcher.start()
    try:
        assert wait_for(lambda: all(queue.get(i).status in ("done", "error") for i in [*good, bad]))
        late = queue.submit("00-toy", "late.py", "ok")
        dispatcher.wake()
        assert wait_for(lambda: queue.get(late).status == "done")
    finally:
        dispatcher.stop()
    assert seen.is_set() and not dispatcher.running
    assert all(queue.get(i).status == "done" and queue.get(i).gradings == 1 for i in good)
    assert queue.get(bad).status == "error" and "the grader broke" in queue.get(bad).error


def test_a_grading_cluster_needs_a_worker():
    with pytest.raises(ValueError):
        GradingCluster(workers=0)
