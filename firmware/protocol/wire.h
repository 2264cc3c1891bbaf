// hilswarm wire protocol, version 2 (docs/protocol.md): every constant of the wire format.
//
// Plain C++ (no Arduino headers): compiled into the firmware by avr-gcc and into the host tests
// by g++/clang++. Protocol version and firmware version are separate numbers.
#ifndef HILSWARM_PROTOCOL_WIRE_H
#define HILSWARM_PROTOCOL_WIRE_H

#include <stdint.h>

namespace hilswarm {
namespace wire {

const uint8_t kProtocolVersion = 2;  // 2: BCAST, CONFIG's broadcast id, STALE

// Framing.
const uint8_t kDelimiter = 0x00;
const uint8_t kMaxPayload = 96;                      // type + seq + body [bytes]
const uint8_t kCrcSize = 2;                          // CRC-16 appended little-endian
const uint8_t kMaxFrame = kMaxPayload + kCrcSize;    // decoded frame (payload + CRC)
const uint8_t kMinFrame = 4;                         // type, seq, CRC
const uint8_t kMaxEncoded = kMaxFrame + 1;           // COBS adds one byte per 254 (frame < 254)
const uint8_t kReplyBit = 0x80;                      // reply type = request type | 0x80

// Message types.
const uint8_t kHello = 0x01;
const uint8_t kConfig = 0x02;
const uint8_t kTick = 0x03;
const uint8_t kEstop = 0x04;
const uint8_t kSetId = 0x05;
const uint8_t kBcast = 0x06;  // protocol 2: every robot's outputs, one section per board
const uint8_t kError = 0x7F;

// Error codes (body of ERROR: code:u8 detail:u8).
const uint8_t kErrUnknownType = 1;
const uint8_t kErrBadLength = 2;
const uint8_t kErrBadPin = 3;
const uint8_t kErrBadMode = 4;
const uint8_t kErrPinConflict = 5;
const uint8_t kErrNotConfigured = 6;
const uint8_t kErrBadValue = 7;
const uint8_t kErrFrameTooLong = 8;
const uint8_t kErrBadState = 9;

// Status flags (u8 in every reply that carries `status`).
const uint8_t kStatusWatchdogTripped = 0x01;  // event: reported once, then cleared
const uint8_t kStatusEstopped = 0x02;
const uint8_t kStatusNotConfigured = 0x04;
const uint8_t kStatusRxErrors = 0x08;         // event: reported once, then cleared
const uint8_t kStatusReset = 0x10;            // cleared by HELLO
const uint8_t kStatusHwWatchdogReset = 0x20;  // cleared by HELLO
const uint8_t kStatusStale = 0x40;            // never set by a board: a gateway's repeat
const uint8_t kStatusEvents = kStatusWatchdogTripped | kStatusRxErrors;

// BCAST section header (id:u8 hdr:u8 data[hdr & kBcastLengthMask]).
const uint8_t kBcastReplyFlag = 0x80;     // this board answers with BCAST_REPLY
const uint8_t kBcastReservedFlag = 0x40;  // must be 0
const uint8_t kBcastLengthMask = 0x3F;    // section data length [bytes]

// Pin modes.
const uint8_t kModeUnused = 0;
const uint8_t kModeDigitalIn = 1;
const uint8_t kModeDigitalOut = 2;
const uint8_t kModePwm = 3;
const uint8_t kModeServo = 4;
const uint8_t kModeAnalogIn = 5;
const uint8_t kModeDigitalInPullup = 6;
const uint8_t kModeCount = 7;

// Capability bits (u8 per pin in HELLO_REPLY).
const uint8_t kCapDigitalIn = 0x01;
const uint8_t kCapDigitalOut = 0x02;
const uint8_t kCapPwm = 0x04;
const uint8_t kCapServo = 0x08;
const uint8_t kCapAnalogIn = 0x10;
const uint8_t kCapReserved = 0x80;

// Pins (Arduino numbering on ATmega328P; A0-A5 = 14-19) and wire-unit limits.
const uint8_t kPinCount = 20;
const uint8_t kAnalogPinBase = 14;
const uint8_t kPinMaskBits = 24;      // dout and rmask are u24
const uint8_t kServoPinA = 9;         // OC1A
const uint8_t kServoPinB = 10;        // OC1B
const uint16_t kServoMinUs = 500;
const uint16_t kServoMaxUs = 2500;
const uint8_t kPwmMax = 255;
const uint16_t kAdcMax = 1023;

}  // namespace wire
}  // namespace hilswarm

#endif  // HILSWARM_PROTOCOL_WIRE_H
