"""The persistent submission queue and the worker pool."""

from __future__ import annotations

import threading
import time

import pytest

from lab.lessons.store import MAX_ATTEMPTS, SubmissionQueue, WorkerPool


@pytest.fixture()
def queue(tmp_path):
    q = SubmissionQueue(f"sqlite:///{tmp_path / 'submissions.sqlite'}")
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


def test_submissions_survive_a_new_connection(tmp_path):
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    submission_id = SubmissionQueue(url).submit("00-toy", "a.py", "x = 1")
    assert SubmissionQueue(url).get(submission_id).source == "x = 1"


def test_requeue_after_a_crash_and_give_up_after_max_attempts(queue):
    submission_id = queue.submit("00-toy", "a.py", "x = 1")
    for attempt in range(1, MAX_ATTEMPTS + 1):
        assert queue.claim().attempts == attempt
        assert queue.requeue_running() == (1 if attempt < MAX_ATTEMPTS else 0)  # the server "restarts"
    gave_up = queue.get(submission_id)
    assert gave_up.status == "error" and "interrupted" in gave_up.error


def test_each_submission_is_claimed_once_by_concurrent_workers(queue):
    ids = {queue.submit("00-toy", f"{i}.py", "x") for i in range(12)}
    claimed: list[str] = []
    lock = threading.Lock()

    def worker():
        while (job := queue.claim()) is not None:
            with lock:
                claimed.append(job.id)

    threads = [threading.Thread(target=worker) for _ in range(4)]
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


def test_worker_pool_grades_everything_and_records_grader_bugs(queue):
    good = [queue.submit("00-toy", f"{i}.py", "ok") for i in range(3)]
    bad = queue.submit("00-toy", "bug.py", "bug")

    def grade(job):
        if job.source == "bug":
            raise RuntimeError("the grader broke")
        return {"score": 1.0, "tests": [{"max_score": 1.0}]}

    pool = WorkerPool(queue, grade, workers=2, poll_s=0.05)
    pool.start()
    try:
        assert wait_for(lambda: all(queue.get(i).status in ("done", "error") for i in [*good, bad]))
        late = queue.submit("00-toy", "late.py", "ok")
        pool.wake()
        assert wait_for(lambda: queue.get(late).status == "done")
    finally:
        pool.stop()
    assert all(queue.get(i).status == "done" for i in good)
    assert queue.get(bad).status == "error" and "the grader broke" in queue.get(bad).error


def test_worker_pool_needs_a_worker(queue):
    with pytest.raises(ValueError):
        WorkerPool(queue, lambda job: {}, workers=0)
