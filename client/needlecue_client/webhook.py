"""Champion changes at once: a listener for MLflow's registry webhooks on alias changes.

MLflow (3.3+) POSTs `{"entity": "model_version_alias", "action": "created", "data": {"name", "alias",
"version"}}` to a registered URL when an alias moves, signed `X-MLflow-Signature: v1,<base64 HMAC-SHA256
of "<delivery id>.<timestamp>.<body>">` with the webhook's secret (`needlecue team webhook URL`). A
verified call about a model that a followed `ForceClient` uses makes that client ask the registry at
its next `reset()`, so the new champion (or unit calibration) is swapped in between insertions, not
only after `poll_s`. Anything unsigned, wrongly signed, stale (older than `max_age_s`) or replayed is
refused with 401 and changes nothing; polling stays on as the fallback for a missed call.

    listener = AliasListener(secret, port=8765).start()  # then: needlecue team webhook <listener.url>
    listener.follow(client)
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import logging
import threading
import time
from collections import OrderedDict
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

log = logging.getLogger("needlecue_client")

SIGNATURE = "X-MLflow-Signature"
TIMESTAMP = "X-MLflow-Timestamp"
DELIVERY = "X-MLflow-Delivery-Id"
ALIAS_ENTITY = "model_version_alias"
MAX_BODY = 64 * 1024  # an alias event is a few hundred bytes


def signature(secret: str, delivery_id: str, timestamp: str, body: bytes) -> str:
    """What MLflow sends in X-MLflow-Signature for this delivery."""
    signed = f"{delivery_id}.{timestamp}.".encode() + body
    digest = hmac.new(secret.encode(), signed, hashlib.sha256).digest()
    return "v1," + base64.b64encode(digest).decode()


class AliasListener:
    """A small HTTP server on its own thread, taking MLflow's alias webhooks for the clients it follows."""

    def __init__(self, secret: str, host: str = "127.0.0.1", port: int = 0, max_age_s: float = 300.0) -> None:
        if not secret:
            raise ValueError(
                "a webhook listener needs the secret MLflow signs with (NEEDLECUE_WEBHOOK_SECRET)"
            )
        self.secret = secret
        self.max_age_s = max_age_s
        self._clients: list[Any] = []
        self._seen: OrderedDict[str, None] = OrderedDict()  # recent delivery ids: a replay is refused
        self._lock = threading.Lock()
        self.accepted = 0
        self.refused = 0
        self._server = ThreadingHTTPServer((host, port), self._handler())
        self._server.daemon_threads = True
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}/mlflow"

    def follow(self, client: Any) -> None:
        """Tell `client` (a `ForceClient` made by `from_registry`) when one of its models' aliases moves."""
        with self._lock:
            self._clients.append(client)

    def start(self) -> AliasListener:
        self._thread = threading.Thread(target=self._server.serve_forever, name="alias-webhooks", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._server.shutdown()
        self._server.server_close()

    def __enter__(self) -> AliasListener:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.stop()

    def check(self, headers: Any, body: bytes) -> str | None:
        """Why this delivery is refused, or None if it is MLflow's, signed with our secret, fresh and new."""
        sent, stamp, delivery = headers.get(SIGNATURE), headers.get(TIMESTAMP), headers.get(DELIVERY)
        if not (sent and stamp and delivery):
            return "unsigned"
        if not hmac.compare_digest(sent, signature(self.secret, delivery, stamp, body)):
            return "bad signature"
        try:
            age = time.time() - int(stamp)
        except ValueError:
            return "bad timestamp"
        if abs(age) > self.max_age_s:
            return f"stale ({age:.0f} s old)"
        with self._lock:
            if delivery in self._seen:
                return "replayed"
            self._seen[delivery] = None
            while len(self._seen) > 1000:
                self._seen.popitem(last=False)
        return None

    def handle(self, event: dict[str, Any]) -> int:
        """A verified event: the followed clients that use its model poll at their next reset; how many."""
        if event.get("entity") != ALIAS_ENTITY:
            return 0
        name = (event.get("data") or {}).get("name")
        with self._lock:
            hit = [c for c in self._clients if name in c.followed]
        for client in hit:
            client.poll_soon()
        log.info("webhook: %s@%s %s -> %d client(s) poll at their next reset", name,
                 (event.get("data") or {}).get("alias"), event.get("action"), len(hit))  # fmt: skip
        return len(hit)

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        listener = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                length = int(self.headers.get("Content-Length") or 0)
                if length > MAX_BODY:
                    return self._answer(413, "too large")
                body = self.rfile.read(length)
                why = listener.check(self.headers, body)
                if why is not None:
                    listener.refused += 1
                    log.warning("webhook from %s refused: %s", self.client_address[0], why)
                    return self._answer(401, why)
                try:
                    event = json.loads(body)
                except ValueError:
                    return self._answer(400, "not JSON")
                listener.accepted += 1
                n = listener.handle(event if isinstance(event, dict) else {})
                return self._answer(200, f"{n} client(s) notified")

            def _answer(self, code: int, text: str) -> None:
                data = text.encode()
                self.send_response(code)
                self.send_header("Content-Type", "text/plain")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            def log_message(self, *_: object) -> None:  # the refusals are logged above, not every request
                pass

        return Handler
