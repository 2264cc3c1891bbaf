// COBS (consistent overhead byte stuffing): removes every 0x00 so 0x00 can delimit frames.
#ifndef HILSWARM_PROTOCOL_COBS_H
#define HILSWARM_PROTOCOL_COBS_H

#include <stddef.h>
#include <stdint.h>

namespace hilswarm {

// Largest encoded size of `len` input bytes (without the 0x00 delimiter).
// (Frames are short: skip the division, a library call on the AVR, below one full block.)
inline size_t cobs_max_encoded(size_t len) { return len + (len < 254 ? 0 : len / 254) + 1; }

// Encodes `len` bytes of `in` into `out` (no delimiter appended). Returns the encoded length,
// or 0 if `out_cap` is too small (an encoding is never empty).
size_t cobs_encode(const uint8_t* in, size_t len, uint8_t* out, size_t out_cap);

// Streaming COBS decoder: fed the bytes between two delimiters one at a time; never allocates.
// Decoded bytes go to a caller-owned buffer of `capacity` bytes; bytes beyond it are counted but
// not stored (overflow), so memory stays bounded whatever arrives.
class CobsDecoder {
 public:
  CobsDecoder(uint8_t* buffer, uint8_t capacity) : buf_(buffer), cap_(capacity) { reset(); }

  // Starts a new frame.
  void reset() {
    len_ = 0;
    remaining_ = 0;
    code_ = 0xFF;  // "no implied zero before the first block"
    overflow_ = false;
    started_ = false;
  }

  // Feeds one non-zero encoded byte (0x00 is the delimiter and is never fed).
  void feed(uint8_t byte);

  // True once at least one byte of the current frame was fed.
  bool started() const { return started_; }
  // True if the bytes fed so far form a complete COBS encoding (the last block is whole).
  bool complete() const { return remaining_ == 0; }
  // True if the decoded frame did not fit into the buffer.
  bool overflow() const { return overflow_; }
  // Decoded bytes stored so far (valid when !overflow()).
  uint8_t length() const { return len_; }

 private:
  void emit(uint8_t byte);

  uint8_t* buf_;
  uint8_t cap_;
  uint8_t len_;
  uint8_t remaining_;  // data bytes left in the current block
  uint8_t code_;       // code byte of the current block
  bool overflow_;
  bool started_;
};

}  // namespace hilswarm

#endif  // HILSWARM_PROTOCOL_COBS_H
