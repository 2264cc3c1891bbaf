"""The golden frame vectors (firmware/protocol/golden_vectors.json) against the Python codec.

The same file is read by the firmware's host-compiled C++ test, so these vectors are the
contract between the two sides. Two vectors are also worked out by hand here, so the file is
not merely consistent with itself.
"""

from __future__ import annotations

import json
import runpy
from pathlib import Path
from typing import Any

import pytest
from hilswarm.agents.link.board import PIN_COUNT, PROTOCOL_VERSION, PinMode
from hilswarm.agents.link.codec import DropReason, FrameDecoder, encode_message, parse_payload

ROOT = Path(__file__).resolve().parents[2]
VECTORS_PATH = ROOT / "firmware" / "protocol" / "golden_vectors.json"
GENERATOR = ROOT / "scripts" / "make_golden_vectors.py"
DOCUMENT = json.loads(VECTORS_PATH.read_text(encoding="utf-8"))
VECTORS: list[dict[str, Any]] = DOCUMENT["vectors"]


def modes_for(fields: dict[str, Any]) -> list[int]:
    """Pin modes implied by a TICK vector's writes (other pins unused)."""
    modes = [int(PinMode.UNUSED)] * PIN_COUNT
    for w in fields.get("writes", []):
        modes[w["pin"]] = int(PinMode[w["mode"]])
    return modes


def test_file_is_generated_from_the_current_codec() -> None:
    generator = runpy.run_path(str(GENERATOR))
    assert VECTORS_PATH.read_text(encoding="utf-8") == generator["render"](), (
        "golden vectors are stale: run python scripts/make_golden_vectors.py"
    )


def test_document_header() -> None:
    assert DOCUMENT["protocol_version"] == PROTOCOL_VERSION == 2
    names = [v["name"] for v in VECTORS]
    assert len(names) == len(set(names))
    types = {v["fields"]["type"] for v in VECTORS if v["valid"]}
    assert types == {
        "HELLO",
        "HELLO_REPLY",
        "CONFIG",
        "CONFIG_REPLY",
        "TICK",
        "TICK_REPLY",
        "ESTOP",
        "ESTOP_REPLY",
        "SET_ID",
        "SET_ID_REPLY",
        "BCAST",
        "BCAST_REPLY",
        "ERROR",
    }
    assert {v["fields"]["drop_reason"] for v in VECTORS if not v["valid"]} >= {"crc", "too_long"}


@pytest.mark.parametrize("vector", [v for v in VECTORS if v["valid"]], ids=lambda v: v["name"])
def test_valid_vector_decodes_and_reencodes(vector: dict[str, Any]) -> None:
    wire = bytes.fromhex(vector["wire_hex"])
    decoder = FrameDecoder()
    payloads = decoder.feed(wire)
    assert payloads == [bytes.fromhex(vector["payload_hex"])]
    msg = parse_payload(payloads[0], modes=modes_for(vector["fields"]))
    generator = runpy.run_path(str(GENERATOR))
    assert generator["message_fields"](msg) == vector["fields"]
    assert encode_message(msg) == wire
    assert (vector["direction"] == "board_to_host") == bool(
        msg.msg_type & 0x80 or msg.msg_type == 0x7F
    )


@pytest.mark.parametrize("vector", [v for v in VECTORS if not v["valid"]], ids=lambda v: v["name"])
def test_invalid_vector_is_dropped_and_counted(vector: dict[str, Any]) -> None:
    reasons: list[DropReason] = []
    decoder = FrameDecoder(on_drop=reasons.append)
    hello = bytes.fromhex(next(v["wire_hex"] for v in VECTORS if v["name"] == "hello"))
    assert decoder.feed(bytes.fromhex(vector["wire_hex"]) + hello) == [b"\x01\x00"]
    assert [r.value for r in reasons] == [vector["fields"]["drop_reason"]]
    assert decoder.counters.dropped == 1


def test_hand_worked_hello() -> None:
    # payload 01 00; CRC-16/CCITT-FALSE(01 00) = 0x2E3E -> bytes 3E 2E (little-endian);
    # COBS of 01 00 3E 2E: block "01" ends at the zero (code 02), block "3E 2E" (code 03).
    vector = next(v for v in VECTORS if v["name"] == "hello")
    assert vector["wire_hex"] == "0201033e2e00"


def test_hand_worked_blimp_tick_layout() -> None:
    # dout = D2|D7|D13 = 0x2084, rmask = A0 = 1<<14 = 0x004000, then 05 C8, 06 00, 09 DC05.
    vector = next(v for v in VECTORS if v["name"] == "tick_blimp")
    assert vector["payload_hex"] == "030784200000400005c8060009dc05"
    assert len(bytes.fromhex(vector["payload_hex"])) + 2 == 17  # docs/protocol.md
    assert len(bytes.fromhex(vector["wire_hex"])) == 19
    reply = next(v for v in VECTORS if v["name"] == "tick_reply_blimp")
    assert len(bytes.fromhex(reply["wire_hex"])) == 13


def test_hand_worked_broadcast() -> None:
    # Section of id 2: 02, hdr 0x83 (reply | 3 B), levels of D4/D7/D8/D12 = D7|D12 -> bits 1, 3
    # = 0x0A, PWM5 = 200 (C8), PWM6 = 0: the Frisbee's 5 B.
    vector = next(v for v in VECTORS if v["name"] == "bcast_three_frisbees")
    payload = bytes.fromhex(vector["payload_hex"])
    assert payload[:2] == bytes((0x06, 40))
    assert payload[2:] == bytes.fromhex("0103050a14" + "02830ac800" + "03030fff01")
    config = next(v for v in VECTORS if v["name"] == "config_frisbee_bcast_id_2")
    assert bytes.fromhex(config["payload_hex"])[-1] == 2  # the trailing broadcast id
    assert (len(bytes.fromhex(config["payload_hex"])) - 4) % 4 == 1  # 2 + 4n + 1 body bytes
