// numpy dtypes, float32 conversion and the .npy reader/writer of the binary transports.
#include "serve/ndarray.h"

#include <gtest/gtest.h>

#include <cstring>

namespace tether::serve {
namespace {

TEST(NdArray, DtypesAsNumpyWritesThem) {
  EXPECT_EQ(parse_dtype("<f4"), DType::f32);
  EXPECT_EQ(parse_dtype("|u1"), DType::u8);
  EXPECT_EQ(parse_dtype("=f8"), DType::f64);
  EXPECT_EQ(parse_dtype("|b1"), DType::boolean);
  EXPECT_THROW(parse_dtype("|O"), ArrayError);
  EXPECT_THROW(parse_dtype(">f4"), ArrayError);
  EXPECT_THROW(parse_dtype("<U5"), ArrayError);
  EXPECT_THROW(parse_dtype("|V8"), ArrayError);
  EXPECT_THROW(parse_dtype(""), ArrayError);
}

TEST(NdArray, ShapeMustMatchTheBytes) {
  std::string data(24, '\0');
  EXPECT_NO_THROW(make_array(DType::f32, {2, 3}, data));
  EXPECT_THROW(make_array(DType::f32, {2, 4}, data), ArrayError);
  EXPECT_THROW(make_array(DType::f32, {-2, -3}, data), ArrayError);
  EXPECT_THROW(make_array(DType::u8, {1ll << 40, 1ll << 40, 1ll << 40}, data), ArrayError);
}

TEST(NdArray, ConvertsToFloat32) {
  const double d[3] = {1.5, -2, 1e300};
  const NdArray big = make_array(DType::f64, {3}, std::string_view(reinterpret_cast<const char*>(d), sizeof d));
  EXPECT_THROW(to_float32(big), ArrayError);
  const NdArray ok = make_array(DType::f64, {2}, std::string_view(reinterpret_cast<const char*>(d), 16));
  EXPECT_EQ(to_float32(ok), (std::vector<float>{1.5f, -2.f}));
  const uint16_t h[3] = {0x3c00, 0xc000, 0x0001};  // 1, -2, smallest subnormal
  const auto halves = to_float32(make_array(DType::f16, {3}, std::string_view(reinterpret_cast<const char*>(h), 6)));
  EXPECT_EQ(halves[0], 1.f);
  EXPECT_EQ(halves[1], -2.f);
  EXPECT_FLOAT_EQ(halves[2], 5.9604645e-08f);
}

TEST(NdArray, NpyRoundTrip) {
  const float v[6] = {1, 2, 3, 4, 5, 6};
  const std::string file = write_npy(DType::f32, {2, 3}, std::string_view(reinterpret_cast<const char*>(v), sizeof v));
  EXPECT_EQ((file.size() - sizeof v) % 64, 0u);
  const NdArray a = parse_npy(file);
  EXPECT_EQ(a.dtype, DType::f32);
  EXPECT_EQ(a.shape, (std::vector<int64_t>{2, 3}));
  EXPECT_EQ(to_float32(a), std::vector<float>(v, v + 6));
  const NdArray one = parse_npy(write_npy(DType::u8, {4}, "abcd"));
  EXPECT_EQ(one.shape, (std::vector<int64_t>{4}));
  EXPECT_EQ(parse_npy(write_npy(DType::f64, {}, std::string(8, '\0'))).shape.size(), 0u);
}

std::string npy_with_header(const std::string& dict, const std::string& data) {
  std::string out("\x93NUMPY\x01\x00", 8);
  const uint16_t len = uint16_t(dict.size());
  out.append(reinterpret_cast<const char*>(&len), 2);
  return out + dict + data;
}

TEST(NdArray, NpyRefusesWhatItCannotTrust) {
  EXPECT_THROW(parse_npy("not npy at all"), ArrayError);
  EXPECT_THROW(parse_npy(npy_with_header("{'descr': '|O', 'fortran_order': False, 'shape': (1,), }", "12345678")),
               ArrayError);
  EXPECT_THROW(parse_npy(npy_with_header("{'descr': '<f4', 'fortran_order': True, 'shape': (1,), }", "1234")),
               ArrayError);
  EXPECT_THROW(parse_npy(npy_with_header("{'descr': '<f4', 'fortran_order': False, 'shape': (2,), }", "1234")),
               ArrayError);
  EXPECT_THROW(parse_npy(npy_with_header("{'descr': [('a', '<f4')], 'fortran_order': False, 'shape': (1,), }", "1234")),
               ArrayError);
  EXPECT_THROW(parse_npy(npy_with_header("{'descr': '<f4', 'shape': (1,), }", "1234")), ArrayError);
  const std::string good = npy_with_header("{'descr': '<f4', 'fortran_order': False, 'shape': (1,), }", "1234");
  EXPECT_NO_THROW(parse_npy(good));
  for (std::size_t n = 0; n + 4 < good.size(); ++n) EXPECT_THROW(parse_npy(good.substr(0, n)), ArrayError) << n;
}

}  // namespace
}  // namespace tether::serve
