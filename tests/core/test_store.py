"""The session store: lookup, idle expiry, admission within caps on count and memory (never eviction)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

import lab.core.store
from lab.core import CapacityExceeded, Forbidden, InvalidControl, Loaded, Pipeline, SessionStore, UnknownName
from lab.core.errors import RetryLater, TooManyRequests
from lab.core.pipeline import open_session
from lab.core.store import BUSY_RETRY_AFTER, MAX_RETRY_AFTER
from toy_pipeline import TOY, add_noise, gradients


def test_create_get_delete():
    store = SessionStore()
    session = store.create(TOY, options={"count": 2, "size": 4})
    assert store.get(session.id) is session and session.id in store
    store.delete(session.id)
    with pytest.raises(UnknownName):
        store.get(session.id)
    with pytest.raises(UnknownName):
        store.delete(session.id)


def test_a_failed_dataset_load_adds_nothing():
    store = SessionStore()
    with pytest.raises(InvalidControl):
        store.create(TOY, options={"count": 0})
    assert len(store) == 0


def test_idle_sessions_expire(monkeypatch):
    store = SessionStore(idle_seconds=10)
    session = store.create(TOY)
    session.last_used -= 11
    with pytest.raises(UnknownName) as info:
        store.get(session.id)
    assert "expired" in info.value.reason


def test_a_full_store_refuses_instead_of_evicting():
    store = SessionStore(max_sessions=2, idle_seconds=100)
    first, second = store.create(TOY), store.create(TOY)
    first.last_used -= 90  # idle, but not yet expired: still someone's session
    with pytest.raises(RetryLater) as info:
        store.create(TOY)
    assert info.value.status == 503 and info.value.field == "sessions" and "limit 2" in info.value.reason
    assert "expires in 10 s" in info.value.reason and info.value.headers() == {"Retry-After": "10"}
    assert store.ids() == [first.id, second.id]
    first.last_used -= 20  # now idle for longer than idle_seconds: dropped, making room
    third = store.create(TOY)
    assert store.ids() == [second.id, third.id]


def test_busy_sessions_are_never_evicted():
    store = SessionStore(max_sessions=1, idle_seconds=10)
    busy = store.create(TOY)
    busy.running = "lift"
    busy.last_used -= 100  # a running session never expires
    with pytest.raises(RetryLater) as info:
        store.create(TOY)
    assert "every session is in use" in info.value.reason and info.value.retry_after == BUSY_RETRY_AFTER
    assert store.ids() == [busy.id]


def test_the_advised_retry_after_is_bounded():
    store = SessionStore(max_sessions=1, idle_seconds=3600)
    store.create(TOY)
    with pytest.raises(RetryLater) as info:
        store.create(TOY)
    assert info.value.retry_after == MAX_RETRY_AFTER and "expires in 3600 s" in info.value.reason


def test_per_client_cap_is_429_and_leaves_other_clients_room():
    store = SessionStore(max_sessions=10, max_sessions_per_client=2)
    mine = [store.create(TOY, client="10.0.0.1") for _ in range(2)]
    with pytest.raises(TooManyRequests) as info:
        store.create(TOY, client="10.0.0.1")
    assert info.value.status == 429 and "10.0.0.1 holds 2 live sessions" in info.value.reason
    assert "Retry-After" in info.value.headers()
    store.create(TOY, client="10.0.0.2")
    store.create(TOY)  # no client (the viewer): only the total caps apply
    store.delete(mine[0].id)
    store.create(TOY, client="10.0.0.1")  # a deleted session gives its place back
    assert len(store) == 4


def test_memory_cap_refuses_instead_of_evicting():
    size = 64
    one = TOY.dataset(None).load({"count": 8, "size": size})
    nbytes = 8 * size * size * 4
    store = SessionStore(max_bytes=int(nbytes * 1.5))
    a = store.create(TOY, options={"count": 8, "size": size})
    with pytest.raises(RetryLater) as info:
        store.create(TOY, options={"count": 8, "size": size})
    assert info.value.status == 503 and info.value.field == "memory" and "MiB" in info.value.reason
    assert store.ids() == [a.id] and store.memory_bytes() == a.nbytes() >= nbytes
    with pytest.raises(CapacityExceeded) as too_big:  # can never fit: 413, not a retry
        SessionStore(max_bytes=nbytes // 2).create(TOY, options={"count": 8, "size": size})
    assert "MiB" in too_big.value.reason
    assert one.state["images"][0].pixels.dtype == np.float32


def test_a_step_that_grows_past_the_memory_cap_evicts_nothing():
    store = SessionStore(max_bytes=int(2.5 * _toy_bytes()))
    first, second = store.create(TOY), store.create(TOY)
    second.run("add_noise")  # second now holds images and noisy images: over the cap
    store.check_memory()
    assert store.ids() == [first.id, second.id]
    with pytest.raises(RetryLater):
        store.create(TOY)


def _toy_bytes() -> int:
    return SessionStore().create(TOY).nbytes()


def test_the_404_says_truthfully_why_a_session_is_not_there():
    store = SessionStore(idle_seconds=10)
    expired, deleted = store.create(TOY), store.create(TOY)
    expired.last_used -= 11
    store.delete(deleted.id)
    for sid, text in [(expired.id, f"session {expired.id!r} expired after 10 s idle"),
                      (deleted.id, f"session {deleted.id!r} was deleted"),
                      ("0123456789ab", "no such session '0123456789ab'")]:
        with pytest.raises(UnknownName) as info:
            store.get(sid)
        assert info.value.reason.startswith(text) and info.value.field == "session"
        assert store.why_gone(sid).startswith(text)
    with pytest.raises(UnknownName, match="was deleted"):
        store.delete(deleted.id)
    assert "expired" not in store.why_gone(deleted.id)


def test_the_record_of_dropped_ids_is_bounded(monkeypatch):
    monkeypatch.setattr(lab.core.store, "GONE_MEMORY", 3)
    store = SessionStore()
    ids = [store.create(TOY).id for _ in range(5)]
    for sid in ids:
        store.delete(sid)
    assert [store.why_gone(sid).startswith("no such") for sid in ids] == [True, True, False, False, False]


def test_a_loading_session_holds_its_place_and_a_failed_load_gives_it_back():
    store = SessionStore(max_sessions=2, max_sessions_per_client=1)
    seen: list[str] = []

    def load():  # while this one loads, its client's place and one of the server's are taken
        for client in ("a", None):
            try:
                store.check_room(client=client)
            except RetryLater as exc:
                seen.append(f"{client}:{exc.status}")
        return open_session(TOY)

    store.admit(load, client="a")
    assert seen == ["a:429"]
    with pytest.raises(InvalidControl):
        store.create(TOY, options={"count": 0}, client="b")
    store.create(TOY, client="b")  # the failed load left b's place (and the server's) free
    assert len(store) == 2


def test_concurrent_creations_never_overshoot_the_cap():
    store = SessionStore(max_sessions=8)
    outcomes: list[str] = []

    def create():
        try:
            store.create(TOY)
            outcomes.append("ok")
        except RetryLater as exc:
            outcomes.append(str(exc.status))

    threads = [threading.Thread(target=create) for _ in range(40)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert outcomes.count("ok") == 8 and outcomes.count("503") == 32 and len(store) == 8


def test_data_root_limits_the_path_option_of_folder_datasets(tmp_path):
    def folder(*, path: str) -> Loaded:
        return gradients(count=1, size=4)

    pipeline = Pipeline.build(name="f", title="F", summary="", steps=[add_noise], datasets=[folder, gradients])
    (tmp_path / "inside").mkdir()
    store = SessionStore(data_root=tmp_path)
    assert store.create(pipeline, "folder", {"path": str(tmp_path / "inside")}).dataset == "folder"
    with pytest.raises(Forbidden, match="outside the folder"):
        store.create(pipeline, "folder", {"path": str(tmp_path / "inside" / ".." / "..")})
    assert len(store) == 1
    assert store.create(pipeline, "gradients", {"count": 2}).dataset == "gradients"  # no path: no check
    assert SessionStore().create(pipeline, "folder", {"path": "/"}).dataset == "folder"  # no root: anywhere
