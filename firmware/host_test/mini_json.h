// A minimal JSON reader for the host tests (golden vectors): objects, arrays, strings, numbers,
// booleans, null. Throws std::runtime_error with the byte offset on malformed input.
#ifndef HILSWARM_HOST_TEST_MINI_JSON_H
#define HILSWARM_HOST_TEST_MINI_JSON_H

#include <map>
#include <memory>
#include <string>
#include <vector>

namespace mini_json {

struct Value {
  enum Kind { kNull, kBool, kNumber, kString, kArray, kObject } kind = kNull;
  bool boolean = false;
  double number = 0;
  std::string string;
  std::vector<Value> array;
  std::map<std::string, Value> object;

  bool has(const std::string& key) const { return kind == kObject && object.count(key) != 0; }
  // Member access; throws std::runtime_error naming the key if missing.
  const Value& operator[](const std::string& key) const;
  const std::string& str() const;
  long long integer() const;
};

Value parse(const std::string& text);
Value parse_file(const std::string& path);

}  // namespace mini_json

#endif  // HILSWARM_HOST_TEST_MINI_JSON_H
