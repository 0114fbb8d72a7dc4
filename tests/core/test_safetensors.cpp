// safetensors reader: round trip, zero-copy views, and every way a file can lie or be damaged.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <unistd.h>

#include "core/error.h"
#include "core/safetensors.h"
#include "scratch_dir.h"

using namespace tether;
namespace fs = std::filesystem;

namespace {

fs::path temp_path(const std::string& name) { return tether::testing::scratch_dir() / name; }

void write_raw(const fs::path& p, const std::string& header, const std::string& data) {
  std::ofstream out(p, std::ios::binary);
  uint64_t n = header.size();
  char len[8];
  for (int i = 0; i < 8; ++i) len[i] = char((n >> (8 * i)) & 0xff);
  out.write(len, 8);
  out << header << data;
}

// Expects open() to fail with `code` and a message that contains every string in `parts`.
void expect_error(const fs::path& p, ErrorCode code, std::vector<std::string> parts) {
  try {
    SafeTensorsFile::open(p.string());
    FAIL() << "expected an error for " << p;
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), code) << e.what();
    for (const auto& part : parts) EXPECT_NE(std::string(e.what()).find(part), std::string::npos) << e.what();
  }
}

}  // namespace

TEST(SafeTensors, RoundTripAllFloatTypes) {
  const fs::path p = temp_path("roundtrip.safetensors");
  std::vector<float> a = {1.5f, -2.0f, 3.25f, 0.0f, 1e-3f, -7.0f};
  std::vector<uint16_t> bf = {f32_to_bf16(1.5f), f32_to_bf16(-2.0f), f32_to_bf16(3.0f)};
  std::vector<uint16_t> h = {0x3c00, 0xc000, 0x3800};  // 1, -2, 0.5 in IEEE half
  std::map<std::string, Tensor> tensors;
  tensors["a"] = Tensor{DType::f32, {2, 3}, a.data(), nullptr};
  tensors["b"] = Tensor{DType::bf16, {3}, bf.data(), nullptr};
  tensors["h"] = Tensor{DType::f16, {3}, h.data(), nullptr};
  write_safetensors(p.string(), tensors, {{"format", "pt"}});

  SafeTensorsFile f = SafeTensorsFile::open(p.string());
  EXPECT_EQ(f.names().size(), 3u);
  EXPECT_EQ(f.metadata().at("format"), "pt");
  Tensor ta = f.get("a");
  EXPECT_EQ(ta.shape, (Shape{2, 3}));
  EXPECT_EQ(reinterpret_cast<uintptr_t>(ta.data) % 4, 0u);
  EXPECT_EQ(std::memcmp(ta.data, a.data(), a.size() * 4), 0);
  EXPECT_EQ(f.get("b").to_f32(), (std::vector<float>{1.5f, -2.0f, 3.0f}));
  EXPECT_EQ(f.get("h").to_f32(), (std::vector<float>{1.0f, -2.0f, 0.5f}));
}

TEST(SafeTensors, ViewOutlivesFile) {
  const fs::path p = temp_path("outlive.safetensors");
  std::vector<float> a = {4, 5, 6};
  write_safetensors(p.string(), {{"x", Tensor{DType::f32, {3}, a.data(), nullptr}}});
  Tensor t;
  { t = SafeTensorsFile::open(p.string()).get("x"); }
  EXPECT_EQ(t.to_f32(), a);  // the view keeps the mapping alive
}

TEST(SafeTensors, MissingTensorNamesFileAndTensor) {
  const fs::path p = temp_path("missing.safetensors");
  std::vector<float> a = {1};
  write_safetensors(p.string(), {{"x", Tensor{DType::f32, {1}, a.data(), nullptr}}});
  SafeTensorsFile f = SafeTensorsFile::open(p.string());
  try {
    f.get("model.layers.0.weight");
    FAIL();
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::not_found);
    EXPECT_NE(std::string(e.what()).find("model.layers.0.weight"), std::string::npos);
    EXPECT_NE(std::string(e.what()).find(p.string()), std::string::npos);
  }
}

TEST(SafeTensors, MissingFile) { expect_error(temp_path("nope.safetensors"), ErrorCode::not_found, {"nope"}); }

TEST(SafeTensors, TruncatedFile) {
  const fs::path p = temp_path("trunc.safetensors");
  write_raw(p, R"({"w":{"dtype":"F32","shape":[4],"data_offsets":[0,16]}})", std::string(8, '\0'));
  expect_error(p, ErrorCode::format, {"'w'", "truncated", p.string()});
}

TEST(SafeTensors, TooShortForHeader) {
  const fs::path p = temp_path("short.safetensors");
  std::ofstream(p, std::ios::binary) << "abc";
  expect_error(p, ErrorCode::format, {"too short"});
}

TEST(SafeTensors, HeaderLengthBeyondFile) {
  const fs::path p = temp_path("hlen.safetensors");
  std::ofstream out(p, std::ios::binary);
  const char len[8] = {char(0xff), 0x10, 0, 0, 0, 0, 0, 0};
  out.write(len, 8);
  out << "{}";
  out.close();
  expect_error(p, ErrorCode::format, {"header length"});
}

TEST(SafeTensors, HeaderLiesAboutShape) {
  const fs::path p = temp_path("shape.safetensors");
  write_raw(p, R"({"w":{"dtype":"F32","shape":[3],"data_offsets":[0,16]}})", std::string(16, '\0'));
  expect_error(p, ErrorCode::format, {"'w'", "needs 12 bytes", "span 16"});
}

TEST(SafeTensors, HeaderLiesAboutOffsets) {
  const fs::path p = temp_path("offsets.safetensors");
  write_raw(p, R"({"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]},"b":{"dtype":"F32","shape":[2],"data_offsets":[4,12]}})",
            std::string(12, '\0'));
  expect_error(p, ErrorCode::format, {"overlap"});
  write_raw(p, R"({"a":{"dtype":"F32","shape":[2],"data_offsets":[8,0]}})", std::string(8, '\0'));
  expect_error(p, ErrorCode::format, {"'a'", "begin > end"});
}

TEST(SafeTensors, ShapeOverflow) {
  const fs::path p = temp_path("overflow.safetensors");
  write_raw(p, R"({"w":{"dtype":"F32","shape":[4611686018427387904, 8],"data_offsets":[0,0]}})", "");
  expect_error(p, ErrorCode::format, {"'w'", "overflows"});
  // Zero bytes, but dims beyond int64_t, or whose partial product before the zero overflows Tensor::numel().
  write_raw(p, R"({"w":{"dtype":"U8","shape":[9223372036854775808, 0],"data_offsets":[0,0]}})", "");
  expect_error(p, ErrorCode::format, {"'w'", "overflows"});
  write_raw(p, R"({"w":{"dtype":"U8","shape":[0, 18446744073709551615],"data_offsets":[0,0]}})", "");
  expect_error(p, ErrorCode::format, {"'w'", "overflows"});
  write_raw(p, R"({"w":{"dtype":"U8","shape":[8589934592, 1073741824, 0],"data_offsets":[0,0]}})", "");
  expect_error(p, ErrorCode::format, {"'w'", "overflows"});
  // The largest shapes that fit still load (zero elements, so no data).
  write_raw(p, R"({"w":{"dtype":"U8","shape":[9223372036854775807, 0],"data_offsets":[0,0]}})", "");
  EXPECT_EQ(SafeTensorsFile::open(p.string()).get("w").numel(), 0);
}

TEST(SafeTensors, DeeplyNestedHeaderIsRefused) {
  // A header of nested brackets would overflow the stack when the error message dumps the bad field.
  const fs::path p = temp_path("nested.safetensors");
  const std::size_t depth = 1'000'000;
  write_raw(p, R"({"w":{"dtype":"F32","shape":[)" + std::string(depth, '[') + std::string(depth, ']') +
                   R"(],"data_offsets":[0,0]}})",
            "");
  expect_error(p, ErrorCode::format, {"nests deeper than"});
}

TEST(SafeTensors, UnknownDtype) {
  const fs::path p = temp_path("dtype.safetensors");
  write_raw(p, R"({"w":{"dtype":"F8_E9","shape":[1],"data_offsets":[0,1]}})", std::string(1, '\0'));
  expect_error(p, ErrorCode::unsupported, {"'w'", "F8_E9"});
}

TEST(SafeTensors, MalformedJson) {
  const fs::path p = temp_path("json.safetensors");
  write_raw(p, R"({"w":{"dtype":"F32",)", "");
  expect_error(p, ErrorCode::format, {"not valid JSON"});
  write_raw(p, R"([1,2,3])", "");
  expect_error(p, ErrorCode::format, {"not a JSON object"});
  write_raw(p, R"({"w":{"dtype":"F32","shape":[-1],"data_offsets":[0,4]}})", std::string(4, '\0'));
  expect_error(p, ErrorCode::format, {"'w'", "non-negative"});
  write_raw(p, R"({"w":{"dtype":"F32","shape":[1]}})", std::string(4, '\0'));
  expect_error(p, ErrorCode::format, {"'w'", "data_offsets"});
}

TEST(DType, Bf16RoundsToNearestEven) {
  EXPECT_EQ(f32_to_bf16(1.0f), 0x3f80);
  EXPECT_EQ(bf16_to_f32(f32_to_bf16(1.00390625f)), 1.0f);      // halfway, rounds to even (down)
  EXPECT_EQ(bf16_to_f32(f32_to_bf16(1.01171875f)), 1.015625f);  // halfway, rounds to even (up)
  EXPECT_TRUE(std::isnan(bf16_to_f32(f32_to_bf16(std::nanf("")))));
}

TEST(DType, HalfSubnormalsAndSpecials) {
  EXPECT_EQ(f16_to_f32(0x0001), std::ldexp(1.0f, -24));
  EXPECT_EQ(f16_to_f32(0x7bff), 65504.0f);
  EXPECT_TRUE(std::isinf(f16_to_f32(0x7c00)));
  EXPECT_EQ(f16_to_f32(0x8000), -0.0f);
}

TEST(DType, HalfRoundTripAndRounding) {
  for (uint32_t h = 0; h < 0x10000; ++h) {
    const float f = f16_to_f32(uint16_t(h));
    if (std::isnan(f)) continue;
    EXPECT_EQ(f32_to_f16(f), uint16_t(h)) << h;  // every half survives a round trip
  }
  EXPECT_EQ(f32_to_f16(1.0f + std::ldexp(1.0f, -11)), 0x3c00);  // halfway: to even (down)
  EXPECT_EQ(f32_to_f16(1.0f + 3 * std::ldexp(1.0f, -11)), 0x3c02);  // halfway: to even (up)
  EXPECT_EQ(f32_to_f16(70000.0f), 0x7c00);
  EXPECT_EQ(f32_to_f16(std::ldexp(1.0f, -25) * 1.5f), 0x0001);  // rounds up to the smallest subnormal
  EXPECT_EQ(f32_to_f16(std::ldexp(1.0f, -26)), 0x0000);
}
