"""Generate firmware/protocol/golden_vectors.json from the Python codec.

The vectors pin down the wire protocol (docs/protocol.md) for both sides: the Python tests decode
every vector with the codec, and the firmware's host-compiled C++ test parses/builds the same
frames. Every message type is covered, plus COBS edge cases near the largest payload and frames a
receiver must drop (valid: false).

    python scripts/make_golden_vectors.py           # (re)write the file
    python scripts/make_golden_vectors.py --check   # exit 1 if the file is out of date
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from hilswarm.agents.link.board import PROTOCOL_VERSION, BoardStatus, ErrorCode, PinMode
from hilswarm.agents.link.broadcast import SectionLayout
from hilswarm.agents.link.cobs import cobs_encode
from hilswarm.agents.link.codec import (
    BcastMsg,
    BcastReplyMsg,
    BcastSection,
    ConfigEntry,
    ConfigMsg,
    ConfigReplyMsg,
    ErrorMsg,
    EstopMsg,
    EstopReplyMsg,
    HelloMsg,
    HelloReplyMsg,
    Message,
    PinWrite,
    SetIdMsg,
    SetIdReplyMsg,
    TickMsg,
    TickReplyMsg,
    encode_payload,
    frame_payload,
    mask_of_pins,
)
from hilswarm.agents.link.crc import crc16_bytes

OUTPUT = Path(__file__).resolve().parent.parent / "firmware" / "protocol" / "golden_vectors.json"

#: Capability bytes of an Uno/Duemilanove/Fio (docs/protocol.md, "Pins").
UNO_CAPS = (0x80, 0x80, 0x03, 0x07, 0x03, 0x07, 0x07, 0x03, 0x03, 0x0F, 0x0F, 0x07, 0x03,
            0x03, 0x13, 0x13, 0x13, 0x13, 0x13, 0x13)  # fmt: skip

#: Thesis Blimpduino-like configuration: 6 digital outputs, 2 PWM, 1 servo, 1 analog input.
BLIMP_DOUT = (2, 4, 7, 8, 12, 13)
BLIMP_CONFIG = (
    *(ConfigEntry(p, PinMode.DIGITAL_OUT, 0) for p in BLIMP_DOUT),
    ConfigEntry(5, PinMode.PWM, 0),
    ConfigEntry(6, PinMode.PWM, 0),
    ConfigEntry(9, PinMode.SERVO, 1500),
    ConfigEntry(14, PinMode.ANALOG_IN, 0),
)

#: A Frisbee's board (protocol 2 broadcast vectors): H-bridge directions on D4/D7/D8/D12, PWM on
#: D5/D6, battery on A0.
FRISBEE_CONFIG = (
    ConfigEntry(4, PinMode.DIGITAL_OUT, 0),
    ConfigEntry(5, PinMode.PWM, 0),
    ConfigEntry(6, PinMode.PWM, 0),
    ConfigEntry(7, PinMode.DIGITAL_OUT, 0),
    ConfigEntry(8, PinMode.DIGITAL_OUT, 0),
    ConfigEntry(12, PinMode.DIGITAL_OUT, 0),
    ConfigEntry(14, PinMode.ANALOG_IN, 0),
)
FRISBEE_LAYOUT = SectionLayout.of({e.pin: e.mode for e in FRISBEE_CONFIG})
#: Three Frisbees' outputs of one tick (broadcast id -> (dout, {pwm pin: duty})).
FRISBEE_OUTPUTS = {
    1: (mask_of_pins([4, 8]), {5: 10, 6: 20}),
    2: (mask_of_pins([7, 12]), {5: 200, 6: 0}),
    3: (mask_of_pins([4, 7, 8, 12]), {5: 255, 6: 1}),
}


def _bcast_sections(reply_ids: set[int]) -> tuple[BcastSection, ...]:
    return tuple(
        BcastSection(i, i in reply_ids, FRISBEE_LAYOUT.encode(dout, pwm))
        for i, (dout, pwm) in FRISBEE_OUTPUTS.items()
    )


def _bcast_expect(board_id: int) -> dict[str, Any]:
    """What a Frisbee board with ``board_id`` drives after the broadcast vectors."""
    dout, pwm = FRISBEE_OUTPUTS[board_id]
    return {
        "config": f"config_frisbee_bcast_id_{board_id}",
        "board_id": board_id,
        "dout": dout,
        "pwm": [{"pin": p, "value": v} for p, v in sorted(pwm.items())],
    }


def message_fields(msg: Message) -> dict[str, Any]:
    """Decoded meaning of ``msg`` as plain JSON values (names of enums, lists for tuples)."""
    fields: dict[str, Any] = {
        "type": msg.msg_type.name,
        "type_byte": int(msg.msg_type),
        "seq": msg.seq,
    }
    if isinstance(msg, HelloReplyMsg):
        fields |= {
            "protocol_version": msg.protocol_version,
            "fw_major": msg.fw_major,
            "fw_minor": msg.fw_minor,
            "board_id": msg.board_id,
            "status": msg.status,
            "status_flags": _flags(msg.status),
            "n_pins": len(msg.capabilities),
            "capabilities": list(msg.capabilities),
        }
    elif isinstance(msg, ConfigMsg):
        fields |= {
            "watchdog_ms": msg.watchdog_ms,
            "pins": [
                {"pin": e.pin, "mode": PinMode(e.mode).name, "mode_byte": e.mode, "safe": e.safe}
                for e in msg.entries
            ],
            "bcast_id": msg.bcast_id,
        }
    elif isinstance(msg, ConfigReplyMsg):
        fields |= {
            "status": msg.status,
            "status_flags": _flags(msg.status),
            "n_configured": msg.n_configured,
        }
    elif isinstance(msg, TickMsg):
        fields |= {
            "dout": msg.dout,
            "rmask": msg.rmask,
            "writes": [{"pin": w.pin, "mode": w.mode.name, "value": w.value} for w in msg.writes],
        }
    elif isinstance(msg, TickReplyMsg):
        fields |= {
            "status": msg.status,
            "status_flags": _flags(msg.status),
            "board_time_us": msg.board_time_us,
            "samples": list(msg.samples),
        }
    elif isinstance(msg, BcastMsg):
        fields |= {
            "sections": [
                {"board_id": x.board_id, "reply": x.reply, "data_hex": x.data.hex()}
                for x in msg.sections
            ]
        }
    elif isinstance(msg, BcastReplyMsg):
        fields |= {
            "status": msg.status,
            "status_flags": _flags(msg.status),
            "board_time_us": msg.board_time_us,
            "samples": list(msg.samples),
        }
    elif isinstance(msg, EstopReplyMsg):
        fields |= {"status": msg.status, "status_flags": _flags(msg.status)}
    elif isinstance(msg, SetIdMsg | SetIdReplyMsg):
        fields |= {"board_id": msg.board_id}
    elif isinstance(msg, ErrorMsg):
        fields |= {"code": msg.code, "code_name": ErrorCode(msg.code).name, "detail": msg.detail}
    return fields


def _flags(status: int) -> list[str]:
    return [f.name or "" for f in BoardStatus if f and status & f]


def _vector(name: str, msg: Message, description: str) -> dict[str, Any]:
    payload = encode_payload(msg)
    direction = (
        "board_to_host" if int(msg.msg_type) & 0x80 or msg.msg_type == 0x7F else "host_to_board"
    )
    return {
        "name": name,
        "direction": direction,
        "payload_hex": payload.hex(),
        "wire_hex": frame_payload(payload).hex(),
        "valid": True,
        "description": description,
        "fields": message_fields(msg),
    }


def _invalid(
    name: str, payload: bytes, wire: bytes, *, reason: str, description: str
) -> dict[str, Any]:
    return {
        "name": name,
        "direction": "host_to_board",
        "payload_hex": payload.hex(),
        "wire_hex": wire.hex(),
        "valid": False,
        "description": description,
        "fields": {"drop_reason": reason},
    }


#: Detail byte of each error vector: a pin for pin errors, else the offending request type
#: (0x42 = an unknown type; 0 when the frame could not be read at all).
_ERROR_DETAIL = {
    ErrorCode.UNKNOWN_TYPE: 0x42,
    ErrorCode.BAD_LENGTH: 0x03,
    ErrorCode.BAD_PIN: 20,
    ErrorCode.BAD_MODE: 14,
    ErrorCode.PIN_CONFLICT: 10,
    ErrorCode.NOT_CONFIGURED: 0x03,
    ErrorCode.BAD_VALUE: 9,
    ErrorCode.FRAME_TOO_LONG: 0,
    ErrorCode.BAD_STATE: 0x03,
}


def build_vectors() -> list[dict[str, Any]]:
    """All golden vectors, in a stable order."""
    blimp_modes = {e.pin: PinMode(e.mode) for e in BLIMP_CONFIG}
    all_pins = tuple(ConfigEntry(p, PinMode.DIGITAL_OUT, p % 2) for p in range(2, 20))
    blimp_tick = TickMsg(
        seq=7,
        dout=mask_of_pins([2, 7, 13]),
        rmask=mask_of_pins([14]),
        writes=(
            PinWrite(5, 200, blimp_modes[5]),
            PinWrite(6, 0, blimp_modes[6]),
            PinWrite(9, 1500, blimp_modes[9]),
        ),
    )
    v = [
        _vector("hello", HelloMsg(0), "HELLO with seq 0: empty body"),
        _vector("hello_seq_255", HelloMsg(255), "HELLO with the last seq before wrapping"),
        _vector(
            "hello_reply_uno",
            HelloReplyMsg(
                0,
                PROTOCOL_VERSION,
                1,
                0,
                3,
                BoardStatus.RESET | BoardStatus.NOT_CONFIGURED,
                UNO_CAPS,
            ),
            "Uno after boot: board id 3, RESET and NOT_CONFIGURED set, 20 pins",
        ),
        _vector(
            "hello_reply_id_0",
            HelloReplyMsg(1, PROTOCOL_VERSION, 2, 5, 0, 0, UNO_CAPS),
            "firmware 2.5, board id 0, status 0",
        ),
        _vector(
            "config_blimp",
            ConfigMsg(1, 500, BLIMP_CONFIG),
            "Blimpduino-like CONFIG: 6 digital out, PWM 5/6, servo 9 (safe 1500 us), A0 in, "
            "watchdog 500 ms",
        ),
        _vector(
            "config_empty",
            ConfigMsg(2, 0, ()),
            "CONFIG with no pins and the watchdog disabled: every pin UNUSED",
        ),
        _vector(
            "config_all_pins",
            ConfigMsg(3, 0xFFFF, all_pins),
            "CONFIG of all 18 usable pins as DIGITAL_OUT (safe = pin parity), watchdog "
            "65535 ms: the longest CONFIG (76-byte payload)",
        ),
        _vector(
            "config_inputs",
            ConfigMsg(
                4,
                100,
                (
                    ConfigEntry(2, PinMode.DIGITAL_IN),
                    ConfigEntry(3, PinMode.DIGITAL_IN_PULLUP),
                    ConfigEntry(10, PinMode.SERVO, 2500),
                    ConfigEntry(11, PinMode.PWM, 255),
                    ConfigEntry(19, PinMode.ANALOG_IN),
                ),
            ),
            "inputs (plain and pull-up), servo on 10 safe 2500 us, PWM 11 safe 255, A5 analog",
        ),
        _vector("config_reply", ConfigReplyMsg(1, 0, 10), "CONFIG accepted: 10 pins configured"),
        _vector(
            "tick_blimp",
            blimp_tick,
            "Blimpduino-like TICK: D2/D7/D13 high, sample A0, PWM5=200, PWM6=0, servo9=1500 "
            "us: 17 bytes with CRC, 19 on the wire",
        ),
        _vector(
            "tick_empty",
            TickMsg(8),
            "TICK with nothing to write or read (feeds the watchdog): body of six zero bytes",
        ),
        _vector(
            "tick_servo_extremes",
            TickMsg(
                9,
                0,
                mask_of_pins([2, 3, 19]),
                (PinWrite(10, 500, PinMode.SERVO), PinWrite(11, 255, PinMode.PWM)),
            ),
            "config_inputs modes: sample D2, D3, A5; servo10=500 us, PWM11=255",
        ),
        _vector(
            "tick_reply_blimp",
            TickReplyMsg(7, 0, 123456789, (511,)),
            "reply to tick_blimp: status 0, board time 123456789 us, A0 = 511 counts",
        ),
        _vector(
            "tick_reply_flags",
            TickReplyMsg(
                10, BoardStatus.WATCHDOG_TRIPPED | BoardStatus.RX_ERRORS, 0xFFFFFFFF, (0, 1, 1023)
            ),
            "WATCHDOG_TRIPPED and RX_ERRORS reported; clock at its wrap value; three samples",
        ),
        _vector(
            "tick_reply_no_samples",
            TickReplyMsg(11, BoardStatus.ESTOPPED, 0, ()),
            "ESTOPPED, time 0, no samples",
        ),
        _vector("estop", EstopMsg(12), "ESTOP: empty body"),
        _vector("estop_reply", EstopReplyMsg(12, BoardStatus.ESTOPPED), "ESTOP latched"),
        _vector("set_id", SetIdMsg(13, 3), "SET_ID 3"),
        _vector("set_id_0x0100", SetIdMsg(14, 0x0100), "SET_ID 256: a zero low byte"),
        _vector("set_id_reply", SetIdReplyMsg(13, 3), "id 3 read back from EEPROM"),
        _vector("set_id_reply_max", SetIdReplyMsg(15, 0xFFFF), "id 65535 read back"),
    ]
    # Protocol 2: the packed broadcast.
    for board_id in FRISBEE_OUTPUTS:
        v.append(
            _vector(
                f"config_frisbee_bcast_id_{board_id}",
                ConfigMsg(30 + board_id, 300, FRISBEE_CONFIG, board_id),
                f"a Frisbee's CONFIG (D4/D7/D8/D12 out, PWM 5/6, A0 in, watchdog 300 ms) with "
                f"broadcast id {board_id}: the trailing byte of protocol 2",
            )
        )
    bcast = _vector(
        "bcast_three_frisbees",
        BcastMsg(40, _bcast_sections({2})),
        "BCAST with three Frisbee sections (ids 1, 2, 3; 3 B of data each: levels of "
        "D4/D7/D8/D12, PWM5, PWM6); only id 2 is asked to reply",
    )
    bcast["expect"] = [_bcast_expect(i) for i in FRISBEE_OUTPUTS]
    v.append(bcast)
    silent = _vector(
        "bcast_no_reply",
        BcastMsg(41, _bcast_sections(set())),
        "the same sections, nobody asked to reply: every board applies its own, none answers",
    )
    silent["expect"] = [_bcast_expect(i) for i in FRISBEE_OUTPUTS]
    v.append(silent)
    v.append(
        _vector(
            "bcast_reply",
            BcastReplyMsg(40, 0, 987654, (612,)),
            "board 2's reply to bcast_three_frisbees: status 0, board time, A0 = 612 counts",
        )
    )
    v.append(
        _vector(
            "tick_reply_stale",
            TickReplyMsg(42, BoardStatus.STALE, 987654, (612,)),
            "a TICK_REPLY a gateway answers itself (protocol 2): the robot's last samples and "
            "board time, marked STALE (a board never sets it)",
        )
    )
    for code in ErrorCode:
        detail = _ERROR_DETAIL[code]
        seq = 0 if code == ErrorCode.FRAME_TOO_LONG else 20 + int(code)
        v.append(
            _vector(
                f"error_{code.name.lower()}",
                ErrorMsg(seq, int(code), detail),
                f"ERROR {code.name} (code {int(code)}), detail {detail}",
            )
        )
    # COBS edge cases near the largest payload.
    v.append(
        _vector(
            "max_payload_no_zeros",
            HelloReplyMsg(0x11, PROTOCOL_VERSION, 1, 2, 0x0303, 0x10, tuple(range(1, 88))),
            "96-byte payload (HELLO_REPLY with 87 pins), no zero byte: one 97+ byte COBS block",
        )
    )
    v.append(
        _vector(
            "max_payload_mostly_zeros",
            TickReplyMsg(0, 0, 0, (0,) * 44),
            "95-byte TICK_REPLY of zeros (44 zero samples): a code byte per zero",
        )
    )
    v.append(
        _vector("payload_ends_in_zero", SetIdReplyMsg(1, 0x0000), "payload ending in zero bytes")
    )
    # Frames a receiver must drop.
    good = encode_payload(SetIdMsg(5, 3))
    bad_crc = bytearray(good + crc16_bytes(good))
    bad_crc[-1] ^= 0x01
    v.append(
        _invalid(
            "bad_crc",
            good,
            cobs_encode(bytes(bad_crc)) + b"\x00",
            reason="crc",
            description="SET_ID 3 with the high CRC byte's lowest bit flipped: dropped, "
            "counted, never answered",
        )
    )
    too_long = encode_payload(HelloReplyMsg(0, PROTOCOL_VERSION, 1, 0, 0, 0, (1,) * 87)) + b"\x01"
    v.append(
        _invalid(
            "too_long",
            too_long,
            frame_payload(too_long),
            reason="too_long",
            description="97-byte payload (one more than the maximum): dropped; the "
            "firmware answers ERROR FRAME_TOO_LONG with seq 0",
        )
    )
    short = bytes([0x01, 0x00, 0x00])
    v.append(
        _invalid(
            "short",
            short,
            cobs_encode(short) + b"\x00",
            reason="short",
            description="decodes to 3 bytes (payload_hex), shorter than type + seq + crc: dropped",
        )
    )
    v.append(
        _invalid(
            "bad_cobs",
            b"",
            bytes([0x05, 0x01, 0x02, 0x00]),
            reason="cobs",
            description="code byte 5 points past the end of a 3-byte frame: dropped",
        )
    )
    return v


def build_document() -> dict[str, Any]:
    """The whole JSON document."""
    return {
        "protocol_version": PROTOCOL_VERSION,
        "generator": "scripts/make_golden_vectors.py",
        "vectors": build_vectors(),
    }


def render() -> str:
    """The file's exact text."""
    return json.dumps(build_document(), indent=1) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Write the vectors file, or with ``--check`` report whether it is up to date."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only compare, exit 1 if stale")
    parser.add_argument("--output", type=Path, default=OUTPUT)
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        current = args.output.read_text(encoding="utf-8") if args.output.exists() else ""
        if current != text:
            print(f"{args.output} is out of date: run python scripts/make_golden_vectors.py")
            return 1
        print(f"{args.output} is up to date")
        return 0
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text, encoding="utf-8")
    print(f"wrote {len(build_vectors())} vectors to {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
