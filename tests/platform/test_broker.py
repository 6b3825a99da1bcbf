"""The embedded broker (no Redis): what the platform's process queues while a worker
polls arrives whole, every message once."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

from kombu import Connection, Exchange, Queue

from tests.servers import ROOT

SENT = 400

#: A platform process queueing SENT messages on the broker at argv[1].
PRODUCER = textwrap.dedent(
    f"""
    import sys
    from kombu import Connection, Exchange, Queue

    queue = Queue("steps", Exchange("steps"), routing_key="steps")
    with Connection(sys.argv[1]) as conn:
        producer = conn.Producer()
        for i in range({SENT}):
            producer.publish({{"n": i, "pad": "x" * 4000}}, exchange=queue.exchange,
                             routing_key="steps", declare=[queue])
    """
)


def _embedded_broker_url(var_dir: Path) -> str:
    """The broker URL that iouv.settings chooses without DATABASE_URL and REDIS_URL."""
    env = {k: v for k, v in os.environ.items() if k not in ("DATABASE_URL", "REDIS_URL")}
    env["IOUV_VAR_DIR"] = str(var_dir)
    read = "from iouv import settings; print(settings.CELERY_BROKER_URL)"
    out = subprocess.run(
        [sys.executable, "-c", read], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_messages_queued_by_another_process_while_a_worker_polls_all_arrive_whole(
    tmp_path: Path,
) -> None:
    url = _embedded_broker_url(tmp_path)
    assert str(tmp_path) in url  # a file under var/, no server
    queue = Queue("steps", Exchange("steps"), routing_key="steps")
    received: list[int] = []
    with Connection(url) as conn:
        simple = conn.SimpleQueue(queue)
        producer = subprocess.Popen([sys.executable, "-c", PRODUCER, url], cwd=ROOT)
        try:
            while len(received) < SENT:
                message = simple.get(timeout=20)
                received.append(message.payload["n"])
                message.ack()
        finally:
            assert producer.wait(timeout=30) == 0
        assert simple.qsize() == 0
        simple.close()
    assert sorted(received) == list(range(SENT))
