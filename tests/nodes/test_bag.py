"""Bags without a bus: payload codec, writer and reader, recovery of cut files, info,
export, the errors for files that are not bags, and record / play's when no forwarder serves the bus."""
from __future__ import annotations

import json
import re
import struct
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

import msgs
from msgs import CameraInfo, DisplacementField, Image, MarkerArray, MessageError, SlipState
from nodes.bag.backlog import Backlog, Stamped
from nodes.bag.codec import MESSAGE_ENCODING, RECORDING_END_META, join_frames, split_payload
from nodes.bag.export import export, video_fps
from nodes.bag.info import bag_info, format_info
from nodes.bag.reader import BagError, BagReader, read_bag
from nodes.bag.recover import recover, recover_in_place
from nodes.bag.writer import BagWriter
from nodes.cli import main
from tests.nodes.conftest import Bus, run_fv

T0_NS = 1_700_000_000_000_000_000


def frames_of(msg: msgs.Message, seq: int, node: str, pub_ns: int) -> list:
    """Bus frames of `msg` as a publisher would stamp them."""
    msg.seq, msg.node, msg.pub_ns = seq, node, pub_ns
    return msgs.encode(msg)


def sample_messages(n: int, rng: np.random.Generator, size: tuple[int, int] = (24, 32),
                    dt_ns: list[int] | None = None) -> list[tuple[str, bool, msgs.Message, int]]:
    """(topic, latched, message, log_time_ns): a latched CameraInfo, then `n` frames
    each followed by a field and a slip state; frame i is logged at sum(dt_ns[:i])."""
    h, w = size
    out: list[tuple[str, bool, msgs.Message, int]] = [
        ("/camera/info", True, CameraInfo(stamp_ns=T0_NS, width=w, height=h, K=np.eye(3) * 2, D=np.arange(4.0)), T0_NS)]
    t = T0_NS + 1_000_000
    for i in range(n):
        t += dt_ns[i] if dt_ns else 10_000_000
        data = rng.integers(0, 255, (h, w), dtype=np.uint8)
        field = rng.normal(0, 1, (5, 6, 3)).astype(np.float32)
        out += [("/camera/image", False, Image(stamp_ns=t - 500, data=data), t),
                ("/field", False, DisplacementField(stamp_ns=t - 500, field=field, grid_x_px=np.arange(6.0),
                                                    grid_y_px=np.arange(5.0)), t + 1000),
                ("/slip", False, SlipState(stamp_ns=t - 500, probability=i / n,
                                           window_stamps_ns=np.arange(3)), t + 2000)]
    return out


def write_bag(folder: Path, messages: list[tuple[str, bool, msgs.Message, int]], finished: bool = False,
              **kwargs) -> BagWriter:
    """Write `messages` through BagWriter as if received at their log times; seq counts
    per topic, node "cam" (info, image) or "proc" (others), pub_ns = log time - 100 ns. `finished`:
    end with the per-topic totals a finished recording keeps (count, gaps, first and last log time)."""
    writer = BagWriter(folder, metadata={"fv_recording": {"host": "test"}}, fsync=False, **kwargs)
    writer.attach("launch.yaml", b"nodes: []\n", "application/yaml")
    seqs: dict[str, int] = {}
    for topic, latched, msg, t in messages:
        seq = seqs[topic] = seqs.get(topic, -1) + 1
        node = "cam" if topic.startswith("/camera") else "proc"
        writer.write(topic, node, latched, frames_of(msg, seq, node, t - 100), t)
    if finished:
        writer.add_metadata(RECORDING_END_META, {"per_topic": json.dumps(
            {t: {"count": st.count, "gaps": 0, "first_ns": st.first_ns, "last_ns": st.last_ns}
             for t, st in writer.stats.items()})})
    writer.close()
    return writer


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


@pytest.fixture
def bag(tmp_path: Path, rng: np.random.Generator) -> tuple[Path, list]:
    messages = sample_messages(40, rng)
    write_bag(tmp_path / "run", messages, chunk_size_b=8_000)
    return tmp_path / "run", messages


def test_payload_splits_back_into_the_frames_without_copy(rng: np.random.Generator) -> None:
    image = Image(data=rng.integers(0, 255, (7, 9, 3), dtype=np.uint8), encoding="bgr8")
    for msg in (image,
                MarkerArray(ref_px=np.ones((4, 2), np.float32), cur_px=np.zeros((4, 2), np.float32),
                            valid=np.ones(4, bool), frames_since_seen=np.zeros(4, np.int32), width=640, height=480),
                SlipState(probability=0.25, frame_id="x" * 1500)):  # header longer than one probe
        frames = msgs.encode(msg)
        payload = join_frames(frames)
        header, parts = split_payload(payload, "/t")
        assert header["type"] == msg.TYPE
        assert [bytes(p) for p in parts] == [bytes(f) for f in frames]
        decoded = msgs.decode(parts, "/t")
        assert decoded.scalar_fields() == msg.scalar_fields()
        for name in msg.ARRAYS:
            np.testing.assert_array_equal(getattr(decoded, name), getattr(msg, name))
    with pytest.raises(MessageError, match="'/t', type 'Image', field 'arrays'"):
        split_payload(join_frames(msgs.encode(image))[:-1], "/t")
    with pytest.raises(MessageError, match="header"):
        split_payload(b"\xc1garbage", "/t")


def test_writer_and_reader_round_trip(bag: tuple[Path, list]) -> None:
    path, messages = bag
    reader = BagReader(path)
    topics = reader.topics()
    assert {t: (i.type_name, i.count, i.latched, i.nodes) for t, i in topics.items()} == {
        "/camera/info": ("CameraInfo", 1, True, ["cam"]), "/camera/image": ("Image", 40, False, ["cam"]),
        "/field": ("DisplacementField", 40, False, ["proc"]), "/slip": ("SlipState", 40, False, ["proc"])}
    got = list(read_bag(path))
    assert [(t, m.TYPE, lt) for t, m, lt in got] == [(t, m.TYPE, lt) for t, _, m, lt in messages]
    for (_, msg, _), (_, _, want, _) in zip(got, messages):
        assert msg.stamp_ns == want.stamp_ns and msg.seq == want.seq and msg.pub_ns == want.pub_ns
        for name in msg.ARRAYS:
            np.testing.assert_array_equal(getattr(msg, name), getattr(want, name))
    raw = list(reader.messages(["/slip"]))
    assert [m.sequence for m in raw] == list(range(40))
    assert all(m.publish_time_ns == m.log_time_ns - 100 for m in raw)
    assert [a.name for a in reader.attachments()] == ["launch.yaml"]
    assert reader.metadata() == {"fv_recording": {"host": "test"}}
    assert reader.chunk_stats()["chunks"] > 5 and reader.chunk_stats()["compression"] == ["zstd"]
    with open(reader.files[0], "rb") as f:
        from mcap.reader import make_reader
        summary = make_reader(f).get_summary()
    schema = next(s for s in summary.schemas.values() if s.name == "Image")
    assert schema.encoding == MESSAGE_ENCODING and json.loads(schema.data)["version"] == Image.VERSION
    assert all(c.message_encoding == MESSAGE_ENCODING for c in summary.channels.values())


def test_a_readers_topics_are_worked_out_once_and_each_answer_is_the_callers_own(
        bag: tuple[Path, list], monkeypatch: pytest.MonkeyPatch) -> None:
    """topics() scanned every chunk index per topic on each call (milliseconds on a bag of thousands of
    chunks), and a play asks it in its params' check, its setup and each pass."""
    import nodes.bag.reader
    path, _ = bag
    reader = BagReader(path)
    first = reader.topics()
    first["/slip"].nodes.append("someone")
    first["/slip"].count = 0
    del first["/field"]
    monkeypatch.setattr(nodes.bag.reader, "_latched", lambda channel: pytest.fail("topics worked out again"))
    again = reader.topics()
    monkeypatch.undo()
    assert again == BagReader(path).topics()
    assert list(again) == ["/camera/info", "/camera/image", "/field", "/slip"]
    assert (again["/slip"].count, again["/slip"].nodes) == (40, ["proc"])


def test_split_by_size_and_duration_repeats_attachments(tmp_path: Path, rng: np.random.Generator) -> None:
    messages = sample_messages(60, rng)
    by_size = write_bag(tmp_path / "s", messages, chunk_size_b=4_000, max_bag_size_b=20_000, compression="lz4")
    by_time = write_bag(tmp_path / "d", messages, max_bag_duration_s=0.2, compression="none")
    assert len(by_size.files) > 2 and len(by_time.files) == 4  # 0.601 s: 3 full files of 0.2 s + 1
    for writer in (by_size, by_time):
        reader = BagReader(writer.output)
        assert [(m.topic, m.log_time_ns) for m in reader.messages()] == [(t, lt) for t, _, _, lt in messages]
        assert [a.file for a in reader.attachments()] == reader.files
        assert reader.topics()["/field"].count == 60
        # `fv bag info` lists the launch file once, with the files holding it (it listed it once per file)
        [attached] = bag_info(writer.output)["attachments"]
        assert attached["name"] == "launch.yaml" and attached["files"] == [str(f) for f in reader.files]
        assert f"  launch.yaml (application/yaml, 10 B) in {len(reader.files)} files" in format_info(
            bag_info(writer.output)).splitlines()


def test_read_arguments_of_no_meaning_are_refused_by_name(bag: tuple[Path, list]) -> None:
    """Bounds that end before they start were the reader's error blaming the file as damaged (`fv bag recover`),
    NaN read every message, and one topic given as text was read as its letters (`has no topic '/'`)."""
    path, messages = bag
    reader = BagReader(path)
    with pytest.raises(ValueError, match="end_ns 1000 is before start_ns 2000"):
        list(reader.messages(start_ns=2000, end_ns=1000))
    with pytest.raises(ValueError, match="end_ns nan is not a whole number of ns"):
        list(reader.messages(end_ns=float("nan")))
    assert [t for t, _, _ in read_bag(path, "/slip")] == ["/slip"] * sum(m[0] == "/slip" for m in messages)


def test_latched_and_topic_filter_and_unknown_topic(bag: tuple[Path, list]) -> None:
    path, _ = bag
    assert [t for t, _, _ in read_bag(path, ["/camera/info", "/slip"])][:2] == ["/camera/info", "/slip"]
    with pytest.raises(BagError, match="no topic '/nope'"):
        list(read_bag(path, ["/nope"]))


def bag_chunks(path: Path) -> list:
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        return sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)


def test_recover_keeps_every_complete_chunk(bag: tuple[Path, list], tmp_path: Path) -> None:
    path, messages = bag
    file = BagReader(path).files[0]
    data = file.read_bytes()
    chunks = bag_chunks(file)
    for k in (1, len(chunks) // 2, len(chunks) - 1):
        cut = tmp_path / f"cut{k}.mcap"
        cut.write_bytes(data[:chunks[k].chunk_start_offset + chunks[k].chunk_length // 2])
        with pytest.raises(BagError, match="fv bag recover"):
            BagReader(cut)
        report = recover(cut, tmp_path / f"fixed{k}.mcap")
        expected = [lt for _, _, _, lt in messages if lt <= chunks[k - 1].message_end_time]
        got = [m.log_time_ns for m in BagReader(tmp_path / f"fixed{k}.mcap").messages()]
        assert got == expected and report.messages == len(expected) and report.chunks == k
        assert not report.complete and report.lost_b == cut.stat().st_size - chunks[k].chunk_start_offset
        assert report.attachments == 1 and report.metadata == 1
    whole = recover(file, tmp_path / "whole.mcap")
    assert whole.complete and whole.messages == len(messages) and whole.lost_b == 0
    ended = tmp_path / "ended.mcap"  # cut where a chunk starts: no stretch lost ("lost 0 bytes ... at bytes ")
    ended.write_bytes(data[:chunks[1].chunk_start_offset])
    report = recover(ended, tmp_path / "ended_fixed.mcap")
    assert not report.complete and report.damaged == [] and report.chunks == 1
    assert report.summary_line().endswith("nothing lost: the file ended at a record's end, without its summary")


def test_a_recovery_stopped_part_way_leaves_no_file(bag: tuple[Path, list], tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C during `fv bag recover` left a valid, indexed file of the records copied so far, which looked
    like the whole recovery (and a second run was refused: the output existed); in place, a `.recovering` file."""
    import nodes.bag.recover as recovering
    path, _ = bag
    file = BagReader(path).files[0]
    work = tmp_path / "work"
    work.mkdir()
    cut = work / "cut.mcap"
    cut.write_bytes(file.read_bytes()[:file.stat().st_size * 2 // 3])
    copy, copied = recovering._Copier.copy, []

    def stopped_part_way(self, record: object) -> None:
        copied.append(record)
        if len(copied) == 50:
            raise KeyboardInterrupt
        copy(self, record)

    monkeypatch.setattr(recovering._Copier, "copy", stopped_part_way)
    for run in (lambda: recover(cut, work / "fixed.mcap"), lambda: recover_in_place(cut)):
        copied.clear()
        with pytest.raises(KeyboardInterrupt):
            run()
        assert [p.name for p in work.iterdir()] == ["cut.mcap"]
    monkeypatch.undo()
    assert recover(cut, work / "fixed.mcap").messages > 0


@pytest.mark.parametrize("where", ["inside the first chunk", "inside a middle chunk", "a middle chunk's header"])
def test_recover_skips_a_damaged_chunk_and_keeps_every_other(bag: tuple[Path, list], tmp_path: Path,
                                                             where: str) -> None:
    """64 bytes overwritten in a finished bag: recovery loses that chunk alone (it used to stop there and
    lose every later chunk, saying "at most one chunk"). The first chunk defines the topics: their
    messages in later chunks wait for the summary's definitions."""
    path, messages = bag
    file = BagReader(path).files[0]
    data = bytearray(file.read_bytes())
    chunks = bag_chunks(file)
    k = 0 if where == "inside the first chunk" else len(chunks) // 2
    hit = chunks[k].chunk_start_offset + (0 if "header" in where else chunks[k].chunk_length // 2)
    data[hit:hit + 64] = bytes(range(64))
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    report = recover(damaged, tmp_path / "fixed.mcap")
    lost = chunks[k]
    expected = [lt for _, _, _, lt in messages if not lost.message_start_time <= lt <= lost.message_end_time]
    got = [m.log_time_ns for m in BagReader(tmp_path / "fixed.mcap").messages()]
    assert got == expected and report.messages == len(expected) and report.unplaced_messages == 0
    assert report.chunks == len(chunks) - 1 and not report.complete
    start = lost.chunk_start_offset
    assert [a for a, _ in report.damaged] == [start] and report.damaged[0][1] >= start + lost.chunk_length
    assert "1 damaged or cut stretch(es)" in report.summary_line()


@pytest.mark.parametrize("where", ["header", "metadata", "attachment", "summary"])
def test_a_bag_damaged_outside_its_chunks_is_named_and_recovered(tmp_path: Path, where: str) -> None:
    """Bytes overwritten outside the chunks, which their CRCs do not cover: `fv bag info` and the player ended in
    a traceback (header), an error naming no file (metadata: `'utf-8' codec can't decode ...`), a MemoryError
    (attachment), or read it as it was (summary: the player's thread then died on a KeyError); and `fv bag
    recover` called the file complete and left it as it was."""
    messages = sample_messages(30, np.random.default_rng(2))
    write_bag(tmp_path / "b", messages, finished=True, chunk_size_b=4_000).close()
    file = BagReader(tmp_path / "b").files[0]
    data = bytearray(file.read_bytes())
    summary_start = struct.unpack_from("<Q", data, len(data) - 28)[0]
    hit, size, value = {"header": (9, 64, 0), "metadata": (73, 4, 0xAA), "attachment": (128, 8, 0),
                        "summary": (summary_start + 50, 32, 0)}[where]
    data[hit:hit + size] = bytes([value]) * size
    file.write_bytes(bytes(data))
    with pytest.raises(BagError, match=f"bag {re.escape(str(file))}: .*fv bag recover"):
        bag = BagReader(file)
        bag.metadata(), bag.attachments()
    report = recover_in_place(file)
    assert not report.complete and report.messages == len(messages)
    assert [m.log_time_ns for m in BagReader(file).messages()] == [t for *_, t in messages]


def test_recover_in_place_keeps_the_original(bag: tuple[Path, list], capsys: pytest.CaptureFixture) -> None:
    path, messages = bag
    file = BagReader(path).files[0]
    data = file.read_bytes()
    file.write_bytes(data[:len(data) * 2 // 3])
    assert main(["bag", "recover", str(file), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert 0 < report["messages"] < len(messages) and report["lost_b"] > 0
    assert file.with_name(file.name + ".broken").read_bytes() == data[:len(data) * 2 // 3]
    assert BagReader(path).message_count == report["messages"]
    recovered = file.read_bytes()
    # now complete: left as it is, no copy kept (this said that the .broken of the first run already exists)
    report = recover_in_place(file)
    assert report.complete and "left as it is" in report.summary_line() and file.read_bytes() == recovered
    file.write_bytes(recovered[:len(recovered) // 2])  # damaged again, its first original still beside it
    with pytest.raises(ValueError, match="already exists"):
        recover_in_place(file)
    assert file.read_bytes() == recovered[:len(recovered) // 2]
    left = sorted(p.name for p in file.parent.iterdir() if p.name.startswith(file.name))
    assert left == [file.name, file.name + ".broken"]  # no .recovering
    file.with_name(file.name + ".broken").unlink()
    assert recover_in_place(file).damaged and file.with_name(file.name + ".broken").exists()


@pytest.mark.parametrize("content", [b"", b"not a bag at all" * 10, b"\x89MCAP0\r\n" + b"\x00" * 40])
def test_bad_files_give_one_line_errors(tmp_path: Path, content: bytes, capsys: pytest.CaptureFixture) -> None:
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    with pytest.raises(BagError, match=f"bag {path}: "):
        BagReader(path)
    export_argv = ["bag", "export", str(path), "--topic", "/x", "-o", str(tmp_path / "o.csv")]
    for argv in (["bag", "info", str(path)], export_argv, ["bag", "play", str(path)]):  # play: before the bus's check
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and str(path) in err and "Traceback" not in err
    for verb in ("info", "play"):
        assert main(["bag", verb, str(tmp_path / "missing")]) == 2
        assert f"bag {tmp_path / 'missing'}: no such file" in capsys.readouterr().err


def test_export_keeps_a_file_that_exists_and_refuses_rates_that_mean_nothing(
        bag: tuple[Path, list], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """An export used to replace any file at its output without a word; --fps inf never ended, nan and
    negative rates left empty files."""
    path, _ = bag
    keep = tmp_path / "keep.csv"
    keep.write_text("important\n")
    assert main(["bag", "export", str(path), "--topic", "/slip", "-o", str(keep)]) == 2
    assert "exists and is not empty: pass --force" in capsys.readouterr().err and keep.read_text() == "important\n"
    assert main(["bag", "export", str(path), "--topic", "/slip", "-o", str(keep), "--force"]) == 0
    assert len(keep.read_text().splitlines()) == 41
    frames = tmp_path / "frames"  # a frame folder: --force replaced nothing, and two exports' frames mixed
    assert main(["bag", "export", str(path), "--topic", "/camera/image", "-o", str(frames)]) == 0
    (frames / "notes.txt").write_text("mine\n")
    shorter = tmp_path / "short"
    write_bag(shorter, sample_messages(5, np.random.default_rng(1)))
    assert main(["bag", "export", str(shorter), "--topic", "/camera/image", "-o", str(frames)]) == 2
    assert main(["bag", "export", str(shorter), "--topic", "/camera/image", "-o", str(frames), "--force"]) == 0
    assert len(list(frames.glob("*.png"))) == 5 and (frames / "notes.txt").read_text() == "mine\n"
    for fps in ("inf", "nan", "-5"):
        with pytest.raises(SystemExit):
            main(["bag", "export", str(path), "--topic", "/camera/image", "-o", str(tmp_path / f"{fps}.avi"),
                  "--fps", fps])
        assert "is not a finite number >= 0" in capsys.readouterr().err
        assert not (tmp_path / f"{fps}.avi").exists()


def test_an_export_that_fails_half_way_leaves_no_file_and_keeps_the_one_it_was_to_replace(
        tmp_path: Path, rng: np.random.Generator) -> None:
    """Video, CSV and NPZ exports are written whole or not at all: a camera that changed its mode mid-bag
    stopped a video export at its first frame of the new size and left the frames before it as the video."""
    messages = sample_messages(6, rng) + [
        (t, latched, replace(m, data=np.zeros((48, 64), np.uint8)) if t == "/camera/image" else m, log + 10**9)
        for t, latched, m, log in sample_messages(2, rng)[1:]]
    write_bag(tmp_path / "bag", messages)
    for name in ("v.mp4", "v.avi"):
        with pytest.raises(ValueError, match="frame 6 is 64x48 px, the video 32x24 px"):
            export(tmp_path / "bag", "/camera/image", tmp_path / name)
        assert not (tmp_path / name).exists()
    kept = tmp_path / "kept.avi"
    kept.write_bytes(b"an earlier export")
    with pytest.raises(ValueError, match="frame 6"):
        export(tmp_path / "bag", "/camera/image", kept)
    assert kept.read_bytes() == b"an earlier export"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "kept.avi"]


def test_info_into_a_reader_that_stops_early_ends_quietly(bag: tuple[Path, list]) -> None:
    """`fv bag info BAG | head`: the reader goes away mid-output; the command ends with status 1 and
    says nothing (it printed `fv bag: error: [Errno 32] Broken pipe`)."""
    import subprocess
    import sys
    path, _ = bag
    long_info = ("import sys, nodes.bag.info as info\n"
                 "info.format_info = lambda _: 'x' * 10_000_000  # more than a pipe holds\n"
                 f"from nodes.cli import main\nsys.exit(main(['bag', 'info', {str(path)!r}]))\n")
    proc = subprocess.Popen([sys.executable, "-c", long_info], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout.read(10) == b"x" * 10
    proc.stdout.close()
    assert proc.wait(30) == 1 and proc.stderr.read() == b""


def test_damaged_chunk_is_a_bag_error_when_reading(bag: tuple[Path, list], tmp_path: Path) -> None:
    path, _ = bag
    file = BagReader(path).files[0]
    data = bytearray(file.read_bytes())
    chunk = bag_chunks(file)[2]
    data[chunk.chunk_start_offset + chunk.chunk_length - 40] ^= 0xFF
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    with pytest.raises(BagError, match="damaged data"):
        list(read_bag(damaged))


def test_info_json(bag: tuple[Path, list], capsys: pytest.CaptureFixture) -> None:
    path, _ = bag
    assert main(["bag", "info", str(path), "--json", "--gaps"]) == 0
    info = json.loads(capsys.readouterr().out)
    image = next(t for t in info["topics"] if t["topic"] == "/camera/image")
    assert image["count"] == 40 and image["gaps"] == 0 and image["type"] == "Image"
    assert 39 / info["duration_s"] <= image["rate_hz"] <= 100.0  # without a recording's totals: the chunks' bounds
    assert info["attachments"][0]["name"] == "launch.yaml" and info["metadata"]["fv_recording"]["host"] == "test"
    assert main(["bag", "info", str(path)]) == 0
    text = capsys.readouterr().out
    assert "/camera/image" in text and "launch.yaml" in text
    assert bag_info(path)["messages"] == 121


def test_a_topic_s_rate_is_over_its_own_span(tmp_path: Path, rng: np.random.Generator,
                                             capsys: pytest.CaptureFixture) -> None:
    """`fv bag info` and `fv bag export` divided a topic's count by the whole bag's duration: a camera
    recorded from 2 s after the recording began showed 6.02 Hz instead of 12.5, and its video played at
    half speed. A finished recording keeps each topic's first and last log time."""
    messages = sample_messages(40, rng)  # frames every 10 ms: 100 Hz
    late = [(t, latched, m, ts + (0 if latched else 4_000_000_000)) for t, latched, m, ts in messages]
    write_bag(tmp_path / "late", late, finished=True)
    assert main(["bag", "info", str(tmp_path / "late"), "--json"]) == 0
    rates = {t["topic"]: t["rate_hz"] for t in json.loads(capsys.readouterr().out)["topics"]}
    assert rates["/camera/image"] == pytest.approx(100.0) and rates["/camera/info"] == 0.0
    count, out = export(tmp_path / "late", "/camera/image", tmp_path / "late.mp4")
    cap = cv2.VideoCapture(str(out))
    assert count == 40 and cap.get(cv2.CAP_PROP_FPS) == pytest.approx(100.0)
    cap.release()


def test_one_file_of_a_split_recording_has_its_own_rate(tmp_path: Path, rng: np.random.Generator) -> None:
    """The whole recording's first and last times (kept in its last file) gave that file alone 10.1 Hz
    for a 100 Hz camera: they count for a bag only when it holds the whole recording."""
    writer = write_bag(tmp_path / "rec", sample_messages(100, rng), finished=True,  # frames every 10 ms
                       max_bag_duration_s=0.3)
    assert len(writer.files) > 2 and BagReader(tmp_path / "rec").topics()["/camera/image"].rate_hz == pytest.approx(100.0)
    assert BagReader(writer.files[-1]).topics()["/camera/image"].rate_hz == pytest.approx(100.0, rel=0.05)


@pytest.mark.parametrize("fps, written", [(97.2568578553616, 97.26), (12.5, 12.5), (6.024, 6.024), (30000.0, 30000.0)])
def test_video_rates_are_rounded_to_what_the_writers_take(fps: float, written: float, tmp_path: Path) -> None:
    """A measured 97.2568578 fps made OpenCV's mp4 writer fail to open (a time base of 1000 / 97257)."""
    assert video_fps(fps) == written
    writer = cv2.VideoWriter(str(tmp_path / "v.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), video_fps(fps), (32, 24))
    assert writer.isOpened()
    writer.release()


def test_a_backlog_abandoned_by_its_writer_counts_every_message_it_will_not_take_as_lost() -> None:
    """A writer that fails abandons the backlog: the message it failed on, those waiting and every one put
    after are counted lost by topic, so that each message put is taken, dropped or lost."""
    def stamped(topic: str) -> Stamped:
        return Stamped(topic, "src", False, [], {}, 0)

    backlog = Backlog(2)
    assert [backlog.put(stamped(t)) for t in ("/a", "/b", "/a")] == [True, True, False]
    taken = backlog.get(0.0)
    backlog.abandon(taken)
    assert not backlog.put(stamped("/b"))
    assert backlog.dropped == {"/a": 1} and backlog.lost == {"/a": 1, "/b": 2} and backlog.total_lost == 3
    assert backlog.get(0.0) is None


def test_export_video_png_csv_npz(bag: tuple[Path, list], tmp_path: Path) -> None:
    path, messages = bag
    images = [m for t, _, m, _ in messages if t == "/camera/image"]
    for suffix in ("mp4", "avi"):
        count, out = export(path, "/camera/image", tmp_path / f"v.{suffix}")
        cap = cv2.VideoCapture(str(out))
        assert count == 40 and int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 40
        assert int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)) == 32
        cap.release()
    count, out = export(path, "/camera/image", tmp_path / "png")
    files = sorted(out.iterdir())
    assert count == 40 and len(files) == 40
    np.testing.assert_array_equal(cv2.imread(str(files[3]), cv2.IMREAD_GRAYSCALE), images[3].data)
    assert export(path, "/slip", tmp_path / "slip.csv")[0] == 40
    rows = (tmp_path / "slip.csv").read_text().splitlines()
    assert rows[0].startswith("log_time_ns,seq,stamp_ns") and "probability" in rows[0] and len(rows) == 41
    export(path, "/field", tmp_path / "field.npz")
    npz = np.load(tmp_path / "field.npz")
    assert npz["field"].shape == (40, 5, 6, 3) and list(npz["seq"]) == list(range(40))
    assert export(path, "/field", tmp_path / "field_data", "npz")[1] == tmp_path / "field_data"  # written as named
    assert np.load(tmp_path / "field_data")["field"].shape == (40, 5, 6, 3)
    with pytest.raises(ValueError, match="not Image"):
        export(path, "/field", tmp_path / "f.mp4")


def test_record_and_play_without_a_bus_stop_naming_it_as_the_topic_tools(bag: tuple[Path, list], bus_env: Bus,
                                                                         tmp_path: Path) -> None:
    """`fv bag record / play` with no forwarder on the bus: exit 2 at once, in the words of `fv topic` (they
    had a copy of its check, with a text of their own), and no bag written."""
    said = f"no forwarder answers on {bus_env.address.url}: no `fv launch` or `fv forwarder` runs on this bus (FV_BUS)"
    for command in (("bag", "record", "-a", "-o", str(tmp_path / "rec")), ("bag", "play", str(bag[0])),
                    ("topic", "list")):
        result = run_fv(*command, timeout_s=20)
        assert result.returncode == 2 and said in result.stderr, (command, result.stderr)
    assert not (tmp_path / "rec").exists()
