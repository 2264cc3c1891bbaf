#include "fake_hal.h"

#include "hal.h"
#include "wire.h"

namespace fake {

Board board;

void reset(bool keep_eeprom) {
  const uint16_t id = board.eeprom_id;
  const bool set = board.eeprom_set;
  board = Board();
  for (int p = 0; p < 20; ++p) {
    board.mode[p] = hilswarm::wire::kModeUnused;
    board.digital_out[p] = board.pwm[p] = board.servo[p] = -1;
  }
  if (keep_eeprom) {
    board.eeprom_id = id;
    board.eeprom_set = set;
  }
}

namespace {

void violation(const std::string& what) {
  ++board.violations;
  board.last_violation = what;
}

bool pin_ok(uint8_t pin, const char* op) {
  if (pin >= 20) {
    violation(std::string(op) + ": pin " + std::to_string(pin) + " out of range");
    return false;
  }
  if (pin <= 1) violation(std::string(op) + ": touched serial pin " + std::to_string(pin));
  return true;
}

}  // namespace

}  // namespace fake

namespace hilswarm {
namespace hal {

using fake::board;
using fake::violation;

void set_pin_mode(uint8_t pin, uint8_t mode) {
  if (!fake::pin_ok(pin, "set_pin_mode")) return;
  if (mode >= wire::kModeCount) violation("set_pin_mode: bad mode");
  board.mode[pin] = mode;
}

void write_digital(uint8_t pin, uint8_t level) {
  if (!fake::pin_ok(pin, "write_digital")) return;
  if (board.mode[pin] != wire::kModeDigitalOut) violation("write_digital on a non-output pin");
  if (level > 1) violation("write_digital level > 1");
  board.digital_out[pin] = level;
  ++board.writes;
}

void write_pwm(uint8_t pin, uint8_t duty) {
  if (!fake::pin_ok(pin, "write_pwm")) return;
  if (board.mode[pin] != wire::kModePwm) violation("write_pwm on a non-PWM pin");
  board.pwm[pin] = duty;
  ++board.writes;
}

void write_servo(uint8_t pin, uint16_t pulse_us) {
  if (!fake::pin_ok(pin, "write_servo")) return;
  if (board.mode[pin] != wire::kModeServo) violation("write_servo on a non-servo pin");
  if (pulse_us < wire::kServoMinUs || pulse_us > wire::kServoMaxUs) {
    violation("write_servo pulse out of range");
  }
  board.servo[pin] = pulse_us;
  ++board.writes;
}

uint8_t read_digital(uint8_t pin) {
  if (!fake::pin_ok(pin, "read_digital")) return 0;
  const uint8_t m = board.mode[pin];
  if (m != wire::kModeDigitalIn && m != wire::kModeDigitalInPullup) {
    violation("read_digital on a non-digital-input pin");
  }
  return board.digital_in[pin];
}

uint16_t read_analog(uint8_t pin) {
  if (!fake::pin_ok(pin, "read_analog")) return 0;
  if (board.mode[pin] != wire::kModeAnalogIn) violation("read_analog on a non-analog pin");
  return board.analog_in[pin];
}

uint16_t load_board_id() { return board.eeprom_set ? board.eeprom_id : 0; }

void store_board_id(uint16_t id) {
  board.eeprom_id = id;
  board.eeprom_set = true;
}

}  // namespace hal
}  // namespace hilswarm
