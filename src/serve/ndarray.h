// Arrays as the binary transports carry them: openpi's msgpack-numpy maps and GR00T's .npy payloads both come down to
// a numpy dtype string, a shape and the raw bytes. Parsed without pickle; object, string, void and big-endian dtypes
// are refused, as are shapes whose byte count disagrees with the data.
#pragma once

#include <cstdint>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace tether::serve {

// An array that cannot be accepted; the message names the problem (the transport adds the field).
class ArrayError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

enum class DType { boolean, u8, i8, u16, i16, u32, i32, u64, i64, f16, f32, f64 };

struct NdArray {
  DType dtype = DType::f32;
  std::vector<int64_t> shape;
  std::string_view data;  // little-endian, C order; a view into the received message
  int64_t elements() const;
};

// numpy's dtype.str ("<f4", "|u1", "<i8", "|b1", "=f4"...) -> DType; throws ArrayError naming it otherwise.
DType parse_dtype(std::string_view descr);
// The dtype.str numpy writes for `t` on a little-endian machine ("<f4", "|u1").
const char* dtype_descr(DType t);
std::size_t dtype_size(DType t);
// A short name for errors: float32, uint8...
const char* dtype_name(DType t);

// Checks the shape (non-negative dims, at most 32 of them, no overflow) against data.size(); throws ArrayError.
NdArray make_array(DType dtype, std::vector<int64_t> shape, std::string_view data);

// An IEEE half (float16) bit pattern as float32, exactly (subnormals, infinities and NaN included).
float half_to_float(uint16_t h);

// Every element as float32 (integers and bool converted, float64 rounded); throws ArrayError for a value that float32
// cannot hold.
std::vector<float> to_float32(const NdArray& a);

// .npy (format 1.0, 2.0 or 3.0): the header dict's descr, fortran_order (must be False) and shape; the array's bytes
// stay a view into `file`. Throws ArrayError saying what is wrong.
NdArray parse_npy(std::string_view file);
// A .npy file (format 1.0) holding `a`.
std::string write_npy(DType dtype, const std::vector<int64_t>& shape, std::string_view data);

}  // namespace tether::serve
