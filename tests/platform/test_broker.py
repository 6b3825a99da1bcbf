"""The embedded broker: a consumer never sees a half-written message."""

from __future__ import annotations

import threading

from kombu import Connection, Exchange, Queue

from iouv.broker import Transport


def test_messages_written_while_a_consumer_polls_all_arrive_whole(tmp_path) -> None:
    (tmp_path / "control").mkdir()
    options = {
        "data_folder_in": str(tmp_path),
        "data_folder_out": str(tmp_path),
        "control_folder": str(tmp_path / "control"),  # else "control/" in the cwd
    }
    queue = Queue("steps", Exchange("steps"), routing_key="steps")
    sent = 400

    def produce() -> None:
        with Connection(transport=Transport, transport_options=options) as conn:
            producer = conn.Producer()
            for i in range(sent):
                producer.publish({"n": i, "pad": "x" * 4000}, exchange=queue.exchange,
                                 routing_key="steps", declare=[queue])  # fmt: skip

    received: list[int] = []
    writer = threading.Thread(target=produce)
    with Connection(transport=Transport, transport_options=options) as conn:
        simple = conn.SimpleQueue(queue)
        writer.start()
        while len(received) < sent:
            message = simple.get(timeout=10)
            received.append(message.payload["n"])
            message.ack()
        simple.close()
    writer.join()
    assert sorted(received) == list(range(sent))
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".partial")]
