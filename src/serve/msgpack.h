// MessagePack for the binary transports (openpi's WebSocket, GR00T's and Tether's ZMQ): a bounded reader into a small
// tree whose strings and binaries are views of the received frame (image bytes are never copied), and a writer.
// Built on msgpuck (Debian's libmsgpuck-dev), which validates a buffer before it is read. Debian 12's msgpack-c and
// msgpack-cxx packages require Boost 1.74, which conflicts with the Boost 1.81 the server is built on, and
// nlohmann::json's MessagePack support cannot read or write the binary map keys openpi's msgpack-numpy uses.
#pragma once

#include <cstdint>
#include <stdexcept>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace tether::serve::msgpack {

// Malformed, truncated or over-limit input; the message says what and where.
class Error : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

enum class Kind { nil, boolean, integer, float32, float64, str, bin, array, map };

const char* kind_name(Kind k);

struct Value {
  Kind kind = Kind::nil;
  bool boolean = false;
  // Kind::integer: the value, and whether it is an unsigned one above INT64_MAX (then only `uinteger` holds it).
  int64_t integer = 0;
  uint64_t uinteger = 0;
  bool above_int64 = false;
  double number = 0;              // Kind::float32 / float64
  std::string_view bytes;         // Kind::str / bin: a view into the parsed buffer
  std::vector<Value> items;       // Kind::array
  std::vector<std::pair<Value, Value>> entries;  // Kind::map, in wire order

  // The special members are spelled out and the destructor defined in msgpack.cpp: with the implicit ones, clang 14
  // with libstdc++ 12 instantiates std::pair<Value, Value> while checking whether Value is default-constructible,
  // needs Value's destructor for it and fails on the half-instantiated pair (the fuzz preset's build).
  Value() = default;
  Value(const Value&) = default;
  Value(Value&&) noexcept = default;
  Value& operator=(const Value&) = default;
  Value& operator=(Value&&) noexcept = default;
  ~Value();

  bool is_nil() const { return kind == Kind::nil; }
  bool is_map() const { return kind == Kind::map; }
  bool is_array() const { return kind == Kind::array; }
  bool is_str() const { return kind == Kind::str; }
  bool is_bin() const { return kind == Kind::bin; }
  bool is_text_or_bin() const { return kind == Kind::str || kind == Kind::bin; }
  bool is_number() const { return kind == Kind::integer || kind == Kind::float32 || kind == Kind::float64; }
  // The value of a number of any kind, as a double.
  double as_double() const;
  // A map's entry whose key is the string or binary `key` (openpi's msgpack-numpy writes binary keys); null if none.
  const Value* find(std::string_view key) const;
};

struct Limits {
  int max_depth = 16;                 // nesting of arrays and maps
  std::size_t max_elements = 1 << 20;  // array items and map entries in all
};

// Parses exactly one value filling the whole buffer (trailing bytes are an error). The buffer must outlive the
// value. Extension types are refused (no protocol here uses them).
Value parse(std::string_view buffer, const Limits& limits = {});

// Appends MessagePack to a string; sizes are the caller's promise (array(n) then n values).
class Writer {
 public:
  void nil();
  void boolean(bool v);
  void integer(int64_t v);
  void uinteger(uint64_t v);
  void float32(float v);
  void float64(double v);
  void str(std::string_view v);
  void bin(std::string_view v);
  void bin(const void* data, std::size_t size) { bin(std::string_view(static_cast<const char*>(data), size)); }
  void array(uint32_t size);
  void map(uint32_t size);
  const std::string& buffer() const { return out_; }
  std::string take() { return std::move(out_); }

 private:
  char* grow(std::size_t n);
  std::string out_;
};

}  // namespace tether::serve::msgpack
