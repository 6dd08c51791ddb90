"""The page a tab was opened at: reading its query (``?session=ID`` ...) and writing its address bar.

How ``?session=ID`` reaches the server: viser's client does not send the page's query string
(its websocket URL drops it). On connect, the viewer sends the tab one line of JavaScript
(viser's ``RunJavascriptMessage``, the message viser itself uses to load plotly) that copies
``window.location.search`` into the tab's localStorage under a one-off key, then reads that key
back with viser's public ``client.local_storage.get_item``. Messages to a client are handled in
order, so the value is there when the read arrives; the key is random per connection, so two
tabs never see each other's query. When a session is opened, the viewer writes ``?session=ID``
into the tab's address bar (``history.replaceState``), so reloading the tab reopens it.
"""

from __future__ import annotations

import logging
import uuid
from typing import Any

log = logging.getLogger("lab.viewer")

#: Query parameters the viewer understands.
QUERY_KEYS = ("session", "module", "dataset", "lesson")


def _run_javascript(client: Any, source: str) -> None:
    from viser import _messages

    client._websock_connection.queue_message(_messages.RunJavascriptMessage(source=source))


def read_query(client: Any, *, timeout: float = 5.0) -> dict[str, str]:
    """The query parameters of the page a viser client was opened at (``?session=ID`` ...).

    See the module docstring: one line of JavaScript copies ``window.location.search`` into the
    tab's localStorage under a random key, read back with ``client.local_storage.get_item``.
    Returns {} when the client cannot answer (no localStorage, timeout).
    """
    from urllib.parse import parse_qsl

    key = f"lab-query-{uuid.uuid4().hex}"
    script = (f'try {{ window.localStorage.setItem("viser-user:{key}", window.location.search); }} '
              'catch (e) {}')
    try:
        _run_javascript(client, script)
        client.flush()
        search = client.local_storage.get_item(key, timeout=timeout)
        client.local_storage.remove_item(key)
    except Exception as exc:  # an old client, blocked storage, a tab closed meanwhile
        log.info("could not read the page query of client %s: %s", getattr(client, "client_id", "?"), exc)
        return {}
    return {k: v for k, v in parse_qsl((search or "").lstrip("?")) if k in QUERY_KEYS}


def set_page_query(client: Any, session_id: str | None = None, **params: str | None) -> None:
    """Write ``?session=ID`` into the tab's address bar (keeping viser's own parameters, dropping
    ``module`` and ``dataset``, which the session replaces); ``params`` set others (None: remove)."""
    changes = dict(params)
    if session_id is not None:
        changes.update(session=session_id, module=None, dataset=None)
    safe = {key: None if value is None else "".join(c for c in value if c.isalnum() or c in "-_")
            for key, value in changes.items()}
    edits = " ".join(f'p.delete("{key}");' if value is None else f'p.set("{key}", "{value}");'
                     for key, value in safe.items())
    script = ("try { const p = new URLSearchParams(window.location.search); " + edits +
              ' window.history.replaceState(null, "", "?" + p.toString()); } catch (e) {}')
    try:
        _run_javascript(client, script)
    except Exception as exc:
        log.info("could not update the page address: %s", exc)


__all__ = ["QUERY_KEYS", "read_query", "set_page_query"]
