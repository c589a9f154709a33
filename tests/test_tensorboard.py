"""TensorBoard event files (jaxden.train.tensorboard): CRC-32C against published check values
and a bitwise reference, the Event encoding against the protobuf library's own decoder, the
record framing (a record cut short, a damaged one), and what a training run writes: every
scalar of metrics.jsonl at its step, a new file per start with older files untouched, and
nothing with ``--no-tensorboard``. (A resumed fine-tuning run's files are checked in
tests/test_finetune.py too.)"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from helpers import build_tiny_dataset, write_train_config

from jaxden.errors import JaxdenError
from jaxden.train import tensorboard as tb
from jaxden.train.workdir import MetricsLog


def bitwise_crc32c(data: bytes) -> int:
    """CRC-32C one bit at a time (no table): the reference for the table-driven form."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def test_crc32c_check_values_and_reference():
    assert tb.crc32c(b"123456789") == 0xE3069283  # the CRC catalogue's check value
    # RFC 3720 (iSCSI) B.4: 32 bytes of 0x00, of 0xFF, ascending 0..31, descending 31..0.
    assert tb.crc32c(bytes(32)) == 0x8A9136AA
    assert tb.crc32c(b"\xff" * 32) == 0x62A8AB43
    assert tb.crc32c(bytes(range(32))) == 0x46DD794E
    assert tb.crc32c(bytes(range(31, -1, -1))) == 0x113FDB5C
    rng = np.random.default_rng(0)
    for size in (0, 1, 7, 64, 999):
        data = rng.bytes(size)
        assert tb.crc32c(data) == bitwise_crc32c(data)
    crc = 0xE3069283
    assert tb.masked_crc32c(b"123456789") == (((crc >> 15) | (crc << 17)) + 0xA282EAD8) % 2**32


def _protobuf_event_class():
    """The Event message (the fields TensorBoard reads) built with the protobuf library."""
    pytest.importorskip("google.protobuf")
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    F = descriptor_pb2.FieldDescriptorProto
    file = descriptor_pb2.FileDescriptorProto(name="jaxden_test_event.proto", package="t",
                                              syntax="proto3")

    def message(name, *fields):
        proto = file.message_type.add(name=name)
        for field_name, number, kind, label, type_name in fields:
            field = proto.field.add(name=field_name, number=number, type=kind, label=label)
            if type_name:
                field.type_name = type_name

    one, many = F.LABEL_OPTIONAL, F.LABEL_REPEATED
    message("Value", ("tag", 1, F.TYPE_STRING, one, ""),
            ("simple_value", 2, F.TYPE_FLOAT, one, ""))
    message("Summary", ("value", 1, F.TYPE_MESSAGE, many, ".t.Value"))
    message("SessionLog", ("status", 1, F.TYPE_INT32, one, ""))
    message("Event", ("wall_time", 1, F.TYPE_DOUBLE, one, ""), ("step", 2, F.TYPE_INT64, one, ""),
            ("file_version", 3, F.TYPE_STRING, one, ""),
            ("summary", 5, F.TYPE_MESSAGE, one, ".t.Summary"),
            ("session_log", 7, F.TYPE_MESSAGE, one, ".t.SessionLog"))
    pool = descriptor_pool.DescriptorPool()
    pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("t.Event"))


def test_events_decode_with_the_protobuf_library():
    Event = _protobuf_event_class()
    first = Event.FromString(tb.encode_event(0, 1.25e9, file_version=tb.FILE_VERSION))
    assert (first.file_version, first.step, first.wall_time) == ("brain.Event:2", 0, 1.25e9)
    scalars = {"loss": 0.1, "val_loss/é": 3.5e-7, "big": 1e39, "lr": -2.0}
    event = Event.FromString(tb.encode_event(2**40 + 3, 1700000000.123456, scalars=scalars))
    assert event.step == 2**40 + 3 and event.wall_time == 1700000000.123456
    decoded = {v.tag: v.simple_value for v in event.summary.value}
    expected = {k: float(np.float32(v)) if abs(v) < 3.4e38 else np.inf for k, v in scalars.items()}
    assert decoded == expected and list(decoded) == list(scalars)
    negative = Event.FromString(tb.encode_event(-5, 0.0, session_status=tb.SESSION_START))
    assert negative.step == -5 and negative.session_log.status == 1
    # our own decoder reads what the library reads
    assert tb.decode_event(event.SerializeToString())["scalars"] == decoded
    assert tb.decode_event(tb.encode_event(-5, 0.0))["step"] == -5


def test_records_are_framed_checked_and_a_cut_last_record_is_left_out(tmp_path):
    writer = tb.EventWriter(tmp_path)
    writer.scalars(3, {"loss": 0.5})
    writer.scalars(4, {})  # nothing to write
    assert writer.path.name.startswith("events.out.tfevents.")
    data = writer.path.read_bytes()
    (length,) = struct.unpack("<Q", data[:8])
    assert struct.unpack("<I", data[8:12])[0] == tb.masked_crc32c(data[:8])
    assert tb.decode_event(data[12:12 + length])["file_version"] == "brain.Event:2"
    events = tb.read_events(writer.path)
    assert [e.get("scalars") for e in events] == [None, {"loss": 0.5}]
    writer.path.write_bytes(data + tb.record_bytes(b"\x10\x07")[:9])  # killed mid-record
    assert len(tb.read_events(writer.path)) == 2
    damaged = bytearray(data)
    damaged[-6] ^= 1  # a bit of the last event's data
    writer.path.write_bytes(bytes(damaged))
    with pytest.raises(JaxdenError, match="bad data checksum"):
        tb.read_events(writer.path)


def _scalars_by_step(folder):
    """{(step, tag): value} over every event file of ``folder``, and the files' events."""
    seen, files = {}, {}
    for path in tb.event_files(folder):
        files[path.name] = tb.read_events(path)
        for event in files[path.name]:
            for tag, value in event.get("scalars", {}).items():
                seen[event["step"], tag] = value
    return seen, files


def _logged_scalars(log_path):
    out = {}
    for line in log_path.read_text().splitlines():
        record = json.loads(line)
        for key, value in record.items():
            if key != "step":
                out[record["step"], key] = float(np.float32(value))
    return out


def test_metrics_log_writes_every_scalar_and_a_new_file_per_start(tmp_path):
    log = MetricsLog(tmp_path / "metrics.jsonl", 0, tensorboard=True)
    log.write({"step": 0, "val_loss": 0.3, "val_baseline_loss": 0.5})
    log.write({"step": 1, "loss": 0.25, "grad_norm": 2.0, "lr": 1e-3, "seconds": 0.1})
    log.write({"step": 2, "loss": 0.2, "grad_norm": 1.5, "lr": 5e-4, "seconds": 0.1})
    (first,) = tb.event_files(tmp_path)
    before = first.read_bytes()
    seen, _ = _scalars_by_step(tmp_path)
    assert seen == _logged_scalars(tmp_path / "metrics.jsonl")
    # resumed from the checkpoint of step 1: the log drops step 2, a new event file starts
    # with its version and a SessionLog START at step 1; the first file is not touched
    log = MetricsLog(tmp_path / "metrics.jsonl", 1, tensorboard=True)
    log.write({"step": 2, "loss": 0.21, "grad_norm": 1.4, "lr": 5e-4, "seconds": 0.2})
    files = tb.event_files(tmp_path)
    assert len(files) == 2 and files[0] == first and first.read_bytes() == before
    events = tb.read_events(files[1])
    assert events[0]["file_version"] == "brain.Event:2"
    assert (events[1]["step"], events[1]["session_status"]) == (1, tb.SESSION_START)
    assert events[2]["scalars"]["loss"] == np.float32(0.21)
    assert not tb.event_files(tmp_path / "none") and MetricsLog(
        tmp_path / "plain.jsonl", 0).events is None  # off unless asked


@pytest.mark.slow  # ~4 s; test_finetune.py checks a resumed run's event files by default
def test_a_training_run_writes_its_scalars_and_resumes_into_a_new_file(tmp_path):
    from jaxden.train.config import load_train_config
    from jaxden.train.loop import train_and_evaluate

    dataset = build_tiny_dataset(tmp_path / "tiny")
    config = load_train_config(write_train_config(tmp_path, dataset, checkpoint_every=1))
    workdir = tmp_path / "run"  # 2 steps: stopped after 1, then resumed
    train_and_evaluate(config, workdir, progress=False, stop_after=1)
    (first,) = tb.event_files(workdir)
    before = first.read_bytes()
    train_and_evaluate(config, workdir, progress=False)
    files = tb.event_files(workdir)
    assert len(files) == 2 and first.read_bytes() == before
    seen, events = _scalars_by_step(workdir)
    logged = _logged_scalars(workdir / "metrics.jsonl")
    assert seen == logged and {"loss", "val_loss", "lr", "grad_norm"} <= {k for _, k in logged}
    assert max(step for step, _ in logged) == 2
    assert events[files[1].name][1]["session_status"] == tb.SESSION_START


def test_no_tensorboard_switch(monkeypatch, tmp_path):
    from jaxden import cli
    from jaxden.train import loop

    parser = cli.build_parser()
    args = parser.parse_args(["train", "c.toml", "--workdir", "w", "--no-tensorboard"])
    assert args.tensorboard is False
    assert parser.parse_args(["train", "c.toml", "--workdir", "w"]).tensorboard is True
    seen = {}
    monkeypatch.setattr(loop, "train_and_evaluate",
                        lambda config, workdir, **options: seen.update(options) or {"step": 1})
    config = write_train_config(tmp_path, tmp_path / "data")  # never read: the loop is stubbed
    assert cli.main(["train", str(config), "--workdir", str(tmp_path / "w"),
                     "--no-tensorboard"]) == 0
    assert seen == {"tensorboard": False}
