#include "cobs.h"

namespace hilswarm {

size_t cobs_encode(const uint8_t* in, size_t len, uint8_t* out, size_t out_cap) {
  if (out_cap < cobs_max_encoded(len)) return 0;
  size_t code_at = 0;  // where the current block's code byte goes
  size_t o = 1;
  uint8_t code = 1;
  for (size_t i = 0; i < len; ++i) {
    if (in[i] == 0) {
      out[code_at] = code;
      code_at = o++;
      code = 1;
    } else {
      out[o++] = in[i];
      if (++code == 0xFF) {
        out[code_at] = code;
        code_at = o++;
        code = 1;
      }
    }
  }
  out[code_at] = code;
  return o;
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
