"""``adnmesh merge``: one run's recordings as one (crafted recordings; the hierarchy's levels
are merged in ``test_hierarchy_run``)."""
import json
from pathlib import Path

from mcap.writer import Writer as McapWriter

from adnmesh.cli import main
from adnmesh.recording import PUBLISHED_METADATA, Recorder, read_recording
from adnmesh.wire.schemas import message_schemas


def record(path: Path, run: dict, messages, published=None, flush_every: int = 0) -> Path:
    """A recording of ``messages``: ``(topic, kind, body, t_send_ns, t_deliver_ns)``
    (flushed to disk every ``flush_every`` of them: a chunk each)."""
    with Recorder(path, metadata=run, schemas=message_schemas()) as recorder:
        for n, (topic, kind, body, t_send, t_deliver) in enumerate(messages, 1):
            payload = json.dumps({"v": 1, "type": kind, "src": "measurement", "seq": t_send,
                                  "t_send_ns": t_send, **body}).encode()
            recorder.write(topic, kind, payload, log_time_ns=t_deliver, publish_time_ns=t_send)
            if flush_every and n % flush_every == 0:
                recorder.flush()
        if published is not None:
            recorder.add_metadata(PUBLISHED_METADATA, published)
    return path


def p_ip(grid: str, t: int, delay: int = 5) -> tuple:
    return (f"adn/{grid}/measurement/p_ip", "p_ip", {"p_ip_w": 1e6 + t}, t, t + delay)


def test_two_sites_recordings_merge_into_one_with_every_message_once(tmp_path, capsys) -> None:
    """Site a recorded its own and one of b's (a message that crossed to it, delivered there
    later than at b); site b its own. Merged: in delivery-time order, the crossing one once
    (its earliest delivery), the published counts of both: every message recorded somewhere."""
    a = record(tmp_path / "a.mcap", {"run_id": "r1", "grid": "a"},
               [p_ip("a", 10), p_ip("b", 20, delay=8), p_ip("a", 30), p_ip("a", 40)],
               {"adn/a/measurement/p_ip": "3"})
    b = record(tmp_path / "b.mcap", {"run_id": "r1", "grid": "b"},
               [p_ip("b", 20), p_ip("b", 40)], {"adn/b/measurement/p_ip": "2"})
    out = tmp_path / "ab.mcap"
    assert main(["merge", str(out), str(a), str(b)]) == 0
    said = capsys.readouterr().out
    assert "5 messages (1 recorded twice, kept once), grids a, b" in said
    merged = read_recording(out)
    assert [(m.topic[4], m.log_time_ns) for m in merged.messages] == [
        ("a", 15), ("b", 25), ("a", 35), ("a", 45), ("b", 45)]   # a tie: the inputs' order
    assert merged.run["run_id"] == "r1" and merged.run["merged_from"] == "a.mcap b.mcap"
    assert merged.metadata["adnmesh.run.2"]["grid"] == "b"
    assert main(["inspect", str(out)]) == 0
    assert "published counts: every message recorded (5 on 2 topics)" in capsys.readouterr().out
    assert not list(tmp_path.glob(".*partial"))          # written beside OUT, then renamed


def test_what_merge_refuses_is_one_line(tmp_path, capsys) -> None:
    a = record(tmp_path / "a.mcap", {"run_id": "r1"}, [p_ip("a", 10)])
    other_run = record(tmp_path / "c.mcap", {"run_id": "r2"}, [p_ip("c", 10)])
    other_type = record(tmp_path / "d.mcap", {"run_id": "r1"},
                        [("adn/a/measurement/p_ip", "p_ref", {"p_ref_w": 1.0}, 10, 10)])
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file")
    raw = tmp_path / "raw.mcap"             # a channel without schema: not adnmesh's
    with raw.open("wb") as f:
        writer = McapWriter(f)
        writer.start()
        channel = writer.register_channel("adn/a/raw", "json", 0)
        writer.add_message(channel, 1, b"{}", 1)
        writer.finish()
    (tmp_path / "link.mcap").symlink_to(a)
    cases = [
        (["merge", str(tmp_path / "o.mcap"), str(a), str(raw)], "has no JSON schema"),
        (["merge", str(tmp_path / "o.mcap"), str(a), str(tmp_path / "link.mcap")],
         "named twice"),
        (["merge", str(tmp_path / "link.mcap"), str(a), str(other_run)],
         "is one of the recordings to merge"),
        (["merge", str(tmp_path / "o.mcap"), str(a), str(other_run)], "of run r2"),
        (["merge", str(tmp_path / "o.mcap"), str(a), str(other_type)], "holds p_ref messages"),
        (["merge", str(a), str(a), str(other_run)], "is one of the recordings to merge"),
        (["merge", str(tmp_path / "o.mcap"), str(a)], "two or more recordings"),
        (["merge", str(tmp_path / "o.mcap"), str(a), str(tmp_path / "junk.mcap")], "junk.mcap"),
        (["merge", str(tmp_path / "o.mcap"), str(a), str(tmp_path / "none.mcap")], "none.mcap"),
    ]
    for argv, said in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and said in err[0], (argv, err)
    assert read_recording(a).messages           # the input named as OUT is untouched


def test_a_truncated_recording_merges_as_far_as_it_was_written(tmp_path, capsys) -> None:
    a = record(tmp_path / "a.mcap", {"run_id": "r1"}, [p_ip("a", t) for t in range(10, 5000, 10)],
               flush_every=50)
    b = record(tmp_path / "b.mcap", {"run_id": "r1"}, [p_ip("b", 7)])
    cut = tmp_path / "cut.mcap"
    data = a.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    recovered = len(read_recording(cut).messages)
    assert 0 < recovered < 499
    b = record(tmp_path / "b.mcap", {"run_id": "r1"}, [p_ip("b", 7)],
               {"adn/b/measurement/p_ip": "1"})
    assert main(["merge", str(tmp_path / "o.mcap"), str(cut), str(b)]) == 0
    assert f"recovered as far as written: {cut}" in capsys.readouterr().out
    assert len(read_recording(tmp_path / "o.mcap").messages) == recovered + 1
    # the killed run's file has no counts: its topics are not checked, b's are
    assert main(["inspect", str(tmp_path / "o.mcap")]) == 0
    printed = capsys.readouterr().out
    assert "every message recorded (1 on 1 topics)" in printed
    assert "not counted: adn/a/measurement/p_ip (cut.mcap has no published counts)" in printed
