#include "cobs.h"

namespace hilswarm {

size_t cobs_encode(const uint8_t* in, size_t len, uint8_t* out, size_t out_cap) {
  if (out_cap < cobs_max_encoded(len)) return 0;
  // Pointers, not indices: this runs for every reply byte before the reply can start, and
  // 16-bit index arithmetic costs the AVR several instructions per byte.
  const uint8_t* const end = in + len;
  uint8_t* code_at = out;  // where the current block's code byte goes
  uint8_t* o = out + 1;
  uint8_t code = 1;
  while (in != end) {
    const uint8_t byte = *in++;
    if (byte == 0) {
      *code_at = code;
      code_at = o++;
      code = 1;
    } else {
      *o++ = byte;
      if (++code == 0xFF) {
        *code_at = code;
        code_at = o++;
        code = 1;
      }
    }
  }
  *code_at = code;
  return static_cast<size_t>(o - out);
}

void CobsDecoder::emit(uint8_t byte) {
  if (len_ < cap_) {
    buf_[len_++] = byte;
  } else {
    overflow_ = true;
  }
}

void CobsDecoder::feed(uint8_t byte) {
  started_ = true;
  if (remaining_ == 0) {
    // A code byte: the previous block (if any, and if shorter than 254) ends with a zero.
    if (code_ != 0xFF) emit(0);
    code_ = byte;
    remaining_ = static_cast<uint8_t>(byte - 1);
  } else {
    emit(byte);
    --remaining_;
  }
}

}  // namespace hilswarm
