"""The message table (``protocol.messages.MESSAGES``) is the only definition of every message: one entry per type
byte, every dataclass field on the wire, sizes that add up, one generic codec with no per-message branch, and
bytes identical to the fixed layouts the protocol documents."""

import ast
import dataclasses
import inspect
import struct

import numpy as np
import pytest

from protocol import messages as m
from protocol.param_table import TABLE_BYTES


def _example(spec: m.MessageSpec):
    """A message of ``spec`` with every field set to a non-default value that survives the wire exactly."""
    kwargs = {}
    for f in spec.fields:
        if f.length_of is not None:
            continue
        if f.fmt == "record":
            n = 3
            for k, member in enumerate(f.record):
                if member.fixed is not None:
                    kwargs[member.name] = np.arange(1, n + 1) * 7.0 / member.fixed.steps_per_unit + k
                else:
                    kwargs[member.name] = np.arange(100, 100 + n, dtype=np.uint32)
        elif f.fmt == "s":
            kwargs[f.name] = "reason é" if f.text else bytes(range(f.count if isinstance(f.count, int) else 9))
        elif f.fmt == "?":
            kwargs[f.name] = True
        elif f.fmt == "f":
            kwargs[f.name] = tuple(float(np.float32(0.25 * (i + 1))) for i in range(int(f.count)))
        else:
            kwargs[f.name] = 5 if f.count == 1 else tuple(range(int(f.count)))
    return spec.cls(**kwargs)


def _equal(a, b) -> bool:
    return a.same_as(b) if isinstance(a, m.CentroidFrame) else a == b


@pytest.mark.parametrize("spec", m.MESSAGES, ids=lambda s: s.name)
def test_every_message_in_the_table_round_trips_with_every_field_set(spec):
    msg = _example(spec)
    data = m.encode(msg)
    assert data[0] == spec.type_id
    back = m.decode(data)
    assert type(back) is spec.cls and _equal(back, msg)
    assert m.encode(back) == data


def test_the_table_has_one_entry_per_type_byte_and_one_class_per_entry():
    assert [s.type_id for s in m.MESSAGES] == sorted(int(t) for t in m.MsgType)
    assert {s.name for s in m.MESSAGES} == {t.name for t in m.MsgType}
    assert len({s.cls for s in m.MESSAGES}) == len(m.MESSAGES) == len(m.MESSAGE_CLASSES)
    assert set(m.COMMAND_TYPES) == {s.cls for s in m.MESSAGES if s.type_id < 0x80}


@pytest.mark.parametrize("spec", m.MESSAGES, ids=lambda s: s.name)
def test_every_dataclass_field_is_a_wire_field_and_nothing_else_is(spec):
    attrs = [f.name for f in dataclasses.fields(spec.cls)]
    on_wire = []
    for f in spec.fields:
        if f.fmt == "record":
            on_wire += [x.name for x in f.record]
        elif f.length_of is None:
            on_wire.append(f.name)
    assert on_wire == attrs
    for f in spec.fields:  # a length field comes right before the field it counts, which names it as its count
        if f.length_of is not None:
            following = spec.fields[spec.fields.index(f) + 1]
            assert following.name == f.length_of and following.count == f.name


@pytest.mark.parametrize("spec", m.MESSAGES, ids=lambda s: s.name)
def test_the_fixed_size_is_what_struct_says_for_the_declared_formats(spec):
    fmt = "<" + m.TYPE_FORMAT + "".join(f"{f.count}{f.fmt}" for f in spec.fields if not f.variable)
    assert spec.fixed_bytes == struct.calcsize(fmt)
    required = {
        a.name: 0
        for a in dataclasses.fields(spec.cls)
        if a.default is dataclasses.MISSING and a.default_factory is dataclasses.MISSING
    }
    empty = spec.cls(**required)  # every variable field empty
    assert len(m.encode(empty)) == spec.fixed_bytes


def test_documented_layouts_are_the_table_layouts():
    # the byte counts the docs and the C side rely on (docs/links.md, protocol/framing.py)
    sizes = {s.name: s.fixed_bytes for s in m.MESSAGES}
    assert sizes["COMMIT"] == 15  # <BHIII: type, tag, crc32, nonce, expected_generation
    assert sizes["PARAM_TABLE"] == 12 + TABLE_BYTES
    assert sizes["CENTROID_FRAME"] == m.FRAME_HEADER_BYTES == 15 and m.STAR_DTYPE.itemsize == 14
    assert sizes["ESTIMATE"] == struct.calcsize("<BHBHIII10f10f")


def test_encode_and_decode_have_no_per_message_branch():
    """The generic codec names no message class or type: everything it knows comes from the table."""
    names = {s.cls.__name__ for s in m.MESSAGES} | {t.name for t in m.MsgType}
    for fn in (m.encode, m.decode, m._encode_value, m._decode_value, m._value_of, m._length_of):
        tree = ast.parse(inspect.getsource(fn).lstrip())
        used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
        used |= {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
        assert not used & names, (fn.__name__, used & names)


def test_an_old_seven_byte_commit_is_refused():
    # a recorded COMMIT from before the nonce existed must not decode as a new one
    old = struct.pack("<BHI", m.MsgType.COMMIT, 8, 0x01020304)
    with pytest.raises(m.DecodeError):
        m.decode(old)


def test_a_boolean_byte_other_than_zero_or_one_is_refused():
    good = m.encode(m.StreamControl(tag=1, enable=True))
    with pytest.raises(m.DecodeError):
        m.decode(good[:-1] + b"\x02")


def test_a_frame_announcing_more_stars_than_the_sensor_holds_is_refused():
    head = struct.pack("<BIqH", m.MsgType.CENTROID_FRAME, 1, 0, m.MAX_STARS + 1)
    with pytest.raises(m.DecodeError):
        m.decode(head + bytes(14 * (m.MAX_STARS + 1)))


def test_fields_of_the_wrong_kind_are_refused_when_encoding():
    with pytest.raises(m.EncodeError):
        m.encode(m.ParamTable(table=7))  # bytes(7) would silently be 7 zero bytes
    with pytest.raises(m.EncodeError):
        m.encode(m.Estimate(values=(1.0,) * 9))
    with pytest.raises(m.EncodeError):
        m.encode(m.Ack(value=-1))
    with pytest.raises(m.EncodeError):
        m.encode("not a message")
