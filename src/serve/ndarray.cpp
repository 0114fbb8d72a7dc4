// numpy dtypes, the .npy format (numpy/lib/format.py describes it: magic, version, little-endian header length, a
// Python-literal dict padded to 64 bytes) and conversion to float32. Hand-written: the header is a tiny, fixed
// subset of Python literal syntax, and no Debian library reads .npy without also executing pickles.
#include "serve/ndarray.h"

#include <cmath>
#include <cstring>
#include <limits>

namespace tether::serve {

namespace {

[[noreturn]] void fail(const std::string& message) { throw ArrayError(message); }

template <typename T>
T load(const char* p) {
  T v;
  std::memcpy(&v, p, sizeof v);
  return v;
}


}  // namespace

float half_to_float(uint16_t h) {
  const uint32_t sign = uint32_t(h & 0x8000) << 16;
  uint32_t exponent = (h >> 10) & 0x1f, mantissa = h & 0x3ff, bits;
  if (exponent == 0) {
    if (mantissa == 0) {
      bits = sign;
    } else {  // subnormal: normalise
      exponent = 127 - 15 + 1;
      while (!(mantissa & 0x400)) {
        mantissa <<= 1;
        --exponent;
      }
      bits = sign | (exponent << 23) | ((mantissa & 0x3ff) << 13);
    }
  } else if (exponent == 31) {
    bits = sign | 0x7f800000u | (mantissa << 13);
  } else {
    bits = sign | ((exponent + 127 - 15) << 23) | (mantissa << 13);
  }
  float f;
  std::memcpy(&f, &bits, sizeof f);
  return f;
}

int64_t NdArray::elements() const {
  int64_t n = 1;
  for (int64_t d : shape) n *= d;
  return n;
}

DType parse_dtype(std::string_view d) {
  if (d.size() < 2) fail("unsupported dtype '" + std::string(d) + "'");
  const char order = d[0];
  const std::string_view kind = d.substr(1);
  if (order == '>') fail("big-endian dtype '" + std::string(d) + "' is not accepted (send little-endian)");
  if (order != '<' && order != '|' && order != '=')
    fail("unsupported dtype '" + std::string(d) + "'");
  if (kind == "b1") return DType::boolean;
  if (kind == "u1") return DType::u8;
  if (kind == "i1") return DType::i8;
  if (kind == "u2") return DType::u16;
  if (kind == "i2") return DType::i16;
  if (kind == "u4") return DType::u32;
  if (kind == "i4") return DType::i32;
  if (kind == "u8") return DType::u64;
  if (kind == "i8") return DType::i64;
  if (kind == "f2") return DType::f16;
  if (kind == "f4") return DType::f32;
  if (kind == "f8") return DType::f64;
  if (!kind.empty() && kind[0] == 'O') fail("object arrays are not accepted (dtype '" + std::string(d) + "')");
  fail("unsupported dtype '" + std::string(d) + "' (accepted: bool, integers, float16/32/64)");
}

const char* dtype_descr(DType t) {
  switch (t) {
    case DType::boolean: return "|b1";
    case DType::u8: return "|u1";
    case DType::i8: return "|i1";
    case DType::u16: return "<u2";
    case DType::i16: return "<i2";
    case DType::u32: return "<u4";
    case DType::i32: return "<i4";
    case DType::u64: return "<u8";
    case DType::i64: return "<i8";
    case DType::f16: return "<f2";
    case DType::f32: return "<f4";
    case DType::f64: return "<f8";
  }
  return "?";
}

const char* dtype_name(DType t) {
  switch (t) {
    case DType::boolean: return "bool";
    case DType::u8: return "uint8";
    case DType::i8: return "int8";
    case DType::u16: return "uint16";
    case DType::i16: return "int16";
    case DType::u32: return "uint32";
    case DType::i32: return "int32";
    case DType::u64: return "uint64";
    case DType::i64: return "int64";
    case DType::f16: return "float16";
    case DType::f32: return "float32";
    case DType::f64: return "float64";
  }
  return "?";
}

std::size_t dtype_size(DType t) {
  switch (t) {
    case DType::boolean:
    case DType::u8:
    case DType::i8: return 1;
    case DType::u16:
    case DType::i16:
    case DType::f16: return 2;
    case DType::u32:
    case DType::i32:
    case DType::f32: return 4;
    case DType::u64:
    case DType::i64:
    case DType::f64: return 8;
  }
  return 1;
}

NdArray make_array(DType dtype, std::vector<int64_t> shape, std::string_view data) {
  if (shape.size() > 32) fail("more than 32 dimensions");
  uint64_t n = 1;
  for (int64_t d : shape) {
    if (d < 0) fail("negative dimension in the shape");
    if (d != 0 && n > std::numeric_limits<uint64_t>::max() / 8 / uint64_t(d)) fail("the shape is too large");
    n *= uint64_t(d);
  }
  if (n * dtype_size(dtype) != data.size())
    fail("the shape holds " + std::to_string(n) + " " + dtype_name(dtype) + " values (" +
         std::to_string(n * dtype_size(dtype)) + " bytes) but the data has " + std::to_string(data.size()) + " bytes");
  return {dtype, std::move(shape), data};
}

std::vector<float> to_float32(const NdArray& a) {
  const auto n = std::size_t(a.elements());
  std::vector<float> out(n);
  const char* p = a.data.data();
  const std::size_t step = dtype_size(a.dtype);
  for (std::size_t i = 0; i < n; ++i, p += step) {
    double v = 0;
    switch (a.dtype) {
      case DType::boolean: v = load<uint8_t>(p) != 0; break;
      case DType::u8: v = load<uint8_t>(p); break;
      case DType::i8: v = load<int8_t>(p); break;
      case DType::u16: v = load<uint16_t>(p); break;
      case DType::i16: v = load<int16_t>(p); break;
      case DType::u32: v = load<uint32_t>(p); break;
      case DType::i32: v = load<int32_t>(p); break;
      case DType::u64: v = double(load<uint64_t>(p)); break;
      case DType::i64: v = double(load<int64_t>(p)); break;
      case DType::f16: out[i] = half_to_float(load<uint16_t>(p)); continue;
      case DType::f32: out[i] = load<float>(p); continue;
      case DType::f64: v = load<double>(p); break;
    }
    if (std::isfinite(v) && std::fabs(v) > double(std::numeric_limits<float>::max()))
      fail("value " + std::to_string(v) + " at index " + std::to_string(i) + " does not fit in float32");
    out[i] = float(v);
  }
  return out;
}

namespace {

// The header dict: {'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), } in any key order.
struct HeaderParser {
  std::string_view s;
  std::size_t i = 0;
  [[noreturn]] void bad(const std::string& what) { fail("npy header: " + what); }
  void ws() {
    while (i < s.size() && (s[i] == ' ' || s[i] == '\n' || s[i] == '\t')) ++i;
  }
  bool eat(char c) {
    ws();
    if (i < s.size() && s[i] == c) {
      ++i;
      return true;
    }
    return false;
  }
  std::string quoted() {
    ws();
    if (i >= s.size() || (s[i] != '\'' && s[i] != '"')) bad("expected a quoted string");
    const char q = s[i++];
    const std::size_t start = i;
    while (i < s.size() && s[i] != q) ++i;
    if (i >= s.size()) bad("unterminated string");
    return std::string(s.substr(start, i++ - start));
  }
  int64_t integer() {
    ws();
    const std::size_t start = i;
    int64_t v = 0;
    while (i < s.size() && s[i] >= '0' && s[i] <= '9') {
      if (v > (std::numeric_limits<int64_t>::max() - 9) / 10) bad("dimension too large");
      v = v * 10 + (s[i++] - '0');
    }
    if (i == start) bad("expected a dimension");
    if (i < s.size() && s[i] == 'L') ++i;  // Python 2 longs
    return v;
  }
};

}  // namespace

NdArray parse_npy(std::string_view file) {
  static const char kMagic[] = "\x93NUMPY";
  if (file.size() < 10 || file.substr(0, 6) != std::string_view(kMagic, 6)) fail("not a .npy file (bad magic)");
  const int major = static_cast<uint8_t>(file[6]);
  std::size_t header_len = 0, offset = 0;
  if (major == 1) {
    header_len = load<uint16_t>(file.data() + 8);
    offset = 10;
  } else if (major == 2 || major == 3) {
    if (file.size() < 12) fail(".npy file truncated in its header");
    header_len = load<uint32_t>(file.data() + 8);
    offset = 12;
  } else {
    fail(".npy format version " + std::to_string(major) + " is not supported");
  }
  if (header_len > file.size() - offset) fail(".npy file truncated in its header");
  HeaderParser h{file.substr(offset, header_len)};
  std::string descr;
  bool have_descr = false, have_order = false, have_shape = false;
  std::vector<int64_t> shape;
  if (!h.eat('{')) h.bad("expected '{'");
  while (!h.eat('}')) {
    const std::string key = h.quoted();
    if (!h.eat(':')) h.bad("expected ':' after '" + key + "'");
    if (key == "descr") {
      h.ws();
      if (h.i < h.s.size() && h.s[h.i] == '[') fail("structured dtypes are not accepted");
      descr = h.quoted();
      have_descr = true;
    } else if (key == "fortran_order") {
      h.ws();
      if (h.s.substr(h.i, 5) == "False") {
        h.i += 5;
      } else if (h.s.substr(h.i, 4) == "True") {
        fail("Fortran-ordered arrays are not accepted (send a C-contiguous array)");
      } else {
        h.bad("fortran_order must be True or False");
      }
      have_order = true;
    } else if (key == "shape") {
      if (!h.eat('(')) h.bad("shape must be a tuple");
      while (!h.eat(')')) {
        shape.push_back(h.integer());
        if (shape.size() > 32) fail("more than 32 dimensions");
        if (!h.eat(',') && !(h.ws(), h.i < h.s.size() && h.s[h.i] == ')')) h.bad("expected ',' or ')' in the shape");
      }
      have_shape = true;
    } else {
      h.bad("unexpected key '" + key + "'");
    }
    if (!h.eat(',') && !(h.ws(), h.i < h.s.size() && h.s[h.i] == '}')) h.bad("expected ',' or '}'");
  }
  if (!have_descr || !have_order || !have_shape) h.bad("needs descr, fortran_order and shape");
  return make_array(parse_dtype(descr), std::move(shape), file.substr(offset + header_len));
}

std::string write_npy(DType dtype, const std::vector<int64_t>& shape, std::string_view data) {
  std::string dict = std::string("{'descr': '") + dtype_descr(dtype) + "', 'fortran_order': False, 'shape': (";
  for (std::size_t i = 0; i < shape.size(); ++i) dict += (i ? ", " : "") + std::to_string(shape[i]);
  dict += shape.size() == 1 ? ",), }" : "), }";  // Python's tuple syntax: (5,) and ()
  // Total header (magic 6 + version 2 + length 2 + dict + newline) padded with spaces to a multiple of 64.
  std::size_t total = 10 + dict.size() + 1;
  dict.append((64 - total % 64) % 64, ' ');
  dict += '\n';
  std::string out("\x93NUMPY\x01\x00", 8);
  const uint16_t len = uint16_t(dict.size());
  out.append(reinterpret_cast<const char*>(&len), 2);
  out += dict;
  out.append(data);
  return out;
}

}  // namespace tether::serve
