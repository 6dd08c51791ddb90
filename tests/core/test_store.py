"""The session store: lookup, idle expiry, caps on count and memory."""

from __future__ import annotations

import numpy as np
import pytest

from lab.core import CapacityExceeded, Forbidden, InvalidControl, Loaded, Pipeline, SessionStore, UnknownName
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


def test_the_least_recently_used_idle_session_makes_room():
    store = SessionStore(max_sessions=2)
    first, second = store.create(TOY), store.create(TOY)
    first.last_used -= 100
    third = store.create(TOY)
    assert store.ids() == [second.id, third.id]


def test_busy_sessions_are_never_evicted():
    store = SessionStore(max_sessions=1)
    busy = store.create(TOY)
    busy.running = "lift"
    with pytest.raises(CapacityExceeded):
        store.create(TOY)
    assert store.ids() == [busy.id]


def test_memory_cap():
    size = 64
    one = TOY.dataset(None).load({"count": 8, "size": size})
    nbytes = 8 * size * size * 4
    store = SessionStore(max_bytes=int(nbytes * 1.5))
    a = store.create(TOY, options={"count": 8, "size": size})
    b = store.create(TOY, options={"count": 8, "size": size})  # evicts a
    assert store.ids() == [b.id] and a.id not in store
    with pytest.raises(CapacityExceeded) as info:
        SessionStore(max_bytes=nbytes // 2).create(TOY, options={"count": 8, "size": size})
    assert "MiB" in info.value.reason
    assert one.state["images"][0].pixels.dtype == np.float32


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
