"""The view on an address other than loopback: a token first, then the page.

``redistro view --bind ADDR`` (not loopback) makes a random token and prints
it once. The server itself draws nothing; each browser that connects gets a
dialog asking for the token, and only one that gives it gets a page of its
own (its scene, panel and, live, the operator's buttons, which still sign
with the session's key). Three wrong tries close the dialog for that
browser; each is counted and printed.
"""

from __future__ import annotations

import hmac
import secrets
import threading
from typing import Any

TRIES = 3


class Gate:
    """Per browser: the token's dialog, then a view of its own."""

    def __init__(self, server: Any, make_view: Any) -> None:
        """make_view(client): the page drawn for one browser (a ``View``)."""
        self.server, self.make_view = server, make_view
        self.token = secrets.token_urlsafe(12)
        self.views: dict[int, Any] = {}
        self.refused = 0
        self.lock = threading.Lock()
        server.on_client_connect(self._connected)
        server.on_client_disconnect(self._gone)

    def _connected(self, client: Any) -> None:
        gui = client.gui
        tries = [0]
        with gui.add_modal("redistro view: this page needs its token") as modal:
            field = gui.add_text("token", initial_value="")
            go = gui.add_button("Open")
            note = gui.add_markdown("the token was printed where the view was started")

        def check(_event: Any) -> None:
            given = str(field.value).strip().encode()
            if hmac.compare_digest(given, self.token.encode()):
                modal.close()
                view = self.make_view(client)
                with self.lock:
                    self.views[client.client_id] = view
                return
            tries[0] += 1
            with self.lock:
                self.refused += 1
            print(f"view: a wrong token from browser {client.client_id}", flush=True)
            if tries[0] >= TRIES:
                note.content = "**wrong token, too many tries**: reload to try again"
                go.disabled = True
            else:
                note.content = f"**wrong token** ({TRIES - tries[0]} tries left)"

        go.on_click(check)

    def _gone(self, client: Any) -> None:
        with self.lock:
            view = self.views.pop(client.client_id, None)
        if view is not None:
            view.stop()

    def close(self) -> None:
        with self.lock:
            views, self.views = list(self.views.values()), {}
        for view in views:
            view.stop()
