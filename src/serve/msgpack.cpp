// MessagePack reading with every length checked against the bytes that remain before it is trusted: msgpuck's
// mp_check alone is not enough for hostile input (its element counter is an int, so a 2^32-1 item array can wrap
// it), so containers are bounded here and scalars are validated one at a time with mp_check.
#include "serve/msgpack.h"

#include <cstring>
#include <limits>

#include <msgpuck.h>

namespace tether::serve::msgpack {

const char* kind_name(Kind k) {
  switch (k) {
    case Kind::nil: return "nil";
    case Kind::boolean: return "bool";
    case Kind::integer: return "integer";
    case Kind::float32: return "float32";
    case Kind::float64: return "float64";
    case Kind::str: return "string";
    case Kind::bin: return "binary";
    case Kind::array: return "array";
    case Kind::map: return "map";
  }
  return "?";
}

Value::~Value() = default;

double Value::as_double() const {
  switch (kind) {
    case Kind::integer: return above_int64 ? double(uinteger) : double(integer);
    case Kind::float32:
    case Kind::float64: return number;
    default: return std::numeric_limits<double>::quiet_NaN();
  }
}

const Value* Value::find(std::string_view key) const {
  if (kind != Kind::map) return nullptr;
  for (const auto& [k, v] : entries)
    if (k.is_text_or_bin() && k.bytes == key) return &v;
  return nullptr;
}

namespace {

struct Reader {
  const char* begin;
  const char* p;
  const char* end;
  Limits limits;
  std::size_t elements = 0;

  [[noreturn]] void fail(const std::string& what) const {
    throw Error("malformed msgpack at byte " + std::to_string(p - begin) + ": " + what);
  }

  // Containers: the header's size from its first byte, checked before mp_decode_array/map read it.
  uint32_t container_size(bool is_map) {
    const auto c = static_cast<uint8_t>(*p);
    const std::size_t header = (c & 0xf0) == (is_map ? 0x80 : 0x90) ? 1 : (c == 0xdc || c == 0xde) ? 3 : 5;
    if (std::size_t(end - p) < header) fail(std::string("truncated ") + (is_map ? "map" : "array") + " header");
    const uint32_t n = is_map ? mp_decode_map(&p) : mp_decode_array(&p);
    // Every item takes at least one byte: a count beyond the bytes left is a lie, refused before any allocation.
    const uint64_t items = uint64_t(n) * (is_map ? 2 : 1);
    if (items > uint64_t(end - p)) fail(std::to_string(n) + " items announced, only " + std::to_string(end - p) + " bytes left");
    elements += n;
    if (elements > limits.max_elements)
      fail("more than " + std::to_string(limits.max_elements) + " array items and map entries in all");
    return n;
  }

  Value value(int depth) {
    if (p >= end) fail("truncated (a value was expected)");
    Value v;
    const mp_type type = mp_typeof(*p);
    if (type == MP_ARRAY || type == MP_MAP) {
      if (depth >= limits.max_depth) fail("nested deeper than " + std::to_string(limits.max_depth) + " levels");
      const bool is_map = type == MP_MAP;
      const uint32_t n = container_size(is_map);
      if (is_map) {
        v.kind = Kind::map;
        v.entries.reserve(n);
        for (uint32_t i = 0; i < n; ++i) {
          Value key = value(depth + 1);
          Value item = value(depth + 1);
          v.entries.emplace_back(std::move(key), std::move(item));
        }
      } else {
        v.kind = Kind::array;
        v.items.reserve(n);
        for (uint32_t i = 0; i < n; ++i) v.items.push_back(value(depth + 1));
      }
      return v;
    }
    // A scalar: validated on its own (its header and, for strings and binaries, its length) before decoding.
    const char* probe = p;
    if (mp_check(&probe, end) != 0) fail("truncated or invalid " + std::string(type == MP_STR ? "string" : type == MP_BIN ? "binary" : "value"));
    switch (type) {
      case MP_NIL: mp_decode_nil(&p); v.kind = Kind::nil; break;
      case MP_BOOL: v.kind = Kind::boolean; v.boolean = mp_decode_bool(&p); break;
      case MP_UINT: {
        v.kind = Kind::integer;
        v.uinteger = mp_decode_uint(&p);
        v.above_int64 = v.uinteger > uint64_t(std::numeric_limits<int64_t>::max());
        v.integer = v.above_int64 ? 0 : int64_t(v.uinteger);
        break;
      }
      case MP_INT: v.kind = Kind::integer; v.integer = mp_decode_int(&p); break;
      case MP_FLOAT: v.kind = Kind::float32; v.number = mp_decode_float(&p); break;
      case MP_DOUBLE: v.kind = Kind::float64; v.number = mp_decode_double(&p); break;
      case MP_STR: {
        uint32_t len = 0;
        const char* s = mp_decode_str(&p, &len);
        v.kind = Kind::str;
        v.bytes = std::string_view(s, len);
        break;
      }
      case MP_BIN: {
        uint32_t len = 0;
        const char* s = mp_decode_bin(&p, &len);
        v.kind = Kind::bin;
        v.bytes = std::string_view(s, len);
        break;
      }
      case MP_EXT: fail("extension types are not accepted");
      default: fail("unknown type byte");
    }
    if (p > end) fail("truncated");
    return v;
  }
};

}  // namespace

Value parse(std::string_view buffer, const Limits& limits) {
  Reader r{buffer.data(), buffer.data(), buffer.data() + buffer.size(), limits};
  if (buffer.empty()) throw Error("malformed msgpack: empty message");
  Value v = r.value(0);
  if (r.p != r.end) r.fail(std::to_string(r.end - r.p) + " trailing bytes after the message");
  return v;
}

char* Writer::grow(std::size_t n) {
  const std::size_t at = out_.size();
  out_.resize(at + n);
  return out_.data() + at;
}

// Each encoder writes at most its mp_sizeof_* bytes; the string is trimmed to what was written.
#define TETHER_MP_WRITE(size_expr, encode_expr)       \
  do {                                                \
    const std::size_t at = out_.size();               \
    char* start = grow(size_expr);                    \
    char* stop = encode_expr;                         \
    out_.resize(at + std::size_t(stop - start));      \
  } while (0)

void Writer::nil() { TETHER_MP_WRITE(mp_sizeof_nil(), mp_encode_nil(start)); }
void Writer::boolean(bool v) { TETHER_MP_WRITE(mp_sizeof_bool(v), mp_encode_bool(start, v)); }
void Writer::integer(int64_t v) {
  if (v >= 0) return uinteger(uint64_t(v));
  TETHER_MP_WRITE(mp_sizeof_int(v), mp_encode_int(start, v));
}
void Writer::uinteger(uint64_t v) { TETHER_MP_WRITE(mp_sizeof_uint(v), mp_encode_uint(start, v)); }
void Writer::float32(float v) { TETHER_MP_WRITE(mp_sizeof_float(v), mp_encode_float(start, v)); }
void Writer::float64(double v) { TETHER_MP_WRITE(mp_sizeof_double(v), mp_encode_double(start, v)); }
void Writer::str(std::string_view v) {
  TETHER_MP_WRITE(mp_sizeof_str(uint32_t(v.size())), mp_encode_str(start, v.data(), uint32_t(v.size())));
}
void Writer::bin(std::string_view v) {
  TETHER_MP_WRITE(mp_sizeof_bin(uint32_t(v.size())), mp_encode_bin(start, v.data(), uint32_t(v.size())));
}
void Writer::array(uint32_t size) { TETHER_MP_WRITE(mp_sizeof_array(size), mp_encode_array(start, size)); }
void Writer::map(uint32_t size) { TETHER_MP_WRITE(mp_sizeof_map(size), mp_encode_map(start, size)); }

#undef TETHER_MP_WRITE

}  // namespace tether::serve::msgpack
