"""``adnmesh merge``: one run's recordings as one (crafted recordings; the hierarchy's levels
are merged in ``test_hierarchy_run``)."""
import json
from pathlib import Path

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


def p_ip(grid: str, t: int) -> tuple:
    return (f"adn/{grid}/measurement/p_ip", "p_ip", {"p_ip_w": 1e6 + t}, t, t + 5)


def test_two_sites_recordings_merge_into_one_with_every_message_once(tmp_path, capsys) -> None:
    """Site a recorded its own and one of b's (a message that crossed to it); site b its own.
    Merged: in delivery-time order, the crossing one once, the published counts of both: the
    check says every message was recorded somewhere."""
    a = record(tmp_path / "a.mcap", {"run_id": "r1", "grid": "a"},
               [p_ip("a", 10), p_ip("b", 20), p_ip("a", 30)],
               {"adn/a/measurement/p_ip": "2"})
    b = record(tmp_path / "b.mcap", {"run_id": "r1", "grid": "b"},
               [p_ip("b", 20), p_ip("b", 40)], {"adn/b/measurement/p_ip": "2"})
    out = tmp_path / "ab.mcap"
    assert main(["merge", str(out), str(a), str(b)]) == 0
    said = capsys.readouterr().out
    assert "4 messages (1 recorded twice, kept once), grids a, b" in said
    merged = read_recording(out)
    assert [m.log_time_ns for m in merged.messages] == [15, 25, 35, 45]
    assert merged.run["run_id"] == "r1" and merged.run["merged_from"] == "a.mcap b.mcap"
    assert merged.metadata["adnmesh.run.2"]["grid"] == "b"
    assert main(["inspect", str(out)]) == 0
    assert "published counts: every message recorded (4 on 2 topics)" in capsys.readouterr().out


def test_what_merge_refuses_is_one_line(tmp_path, capsys) -> None:
    a = record(tmp_path / "a.mcap", {"run_id": "r1"}, [p_ip("a", 10)])
    other_run = record(tmp_path / "c.mcap", {"run_id": "r2"}, [p_ip("c", 10)])
    other_type = record(tmp_path / "d.mcap", {"run_id": "r1"},
                        [("adn/a/measurement/p_ip", "p_ref", {"p_ref_w": 1.0}, 10, 10)])
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file")
    cases = [
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
    assert main(["merge", str(tmp_path / "o.mcap"), str(cut), str(b)]) == 0
    assert f"recovered as far as written: {cut}" in capsys.readouterr().out
    assert len(read_recording(tmp_path / "o.mcap").messages) == recovered + 1
