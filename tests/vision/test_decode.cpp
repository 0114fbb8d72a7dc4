// Decoding parity with PIL's Image.open(...).convert("RGB") for every PNG/JPEG variant in the
// fixtures, and refusal of corrupt, truncated, unsupported and oversized inputs.
#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>

#include "core/error.h"
#include "vision/image.h"
#include "vision_test_util.h"

using namespace tether;
using namespace tether::vision;
using namespace tether::vision::test;

namespace {

const SafeTensorsFile& decode_fixture() {
  static const SafeTensorsFile f = SafeTensorsFile::open(fixture("decode.safetensors"));
  return f;
}

// Compares our decode of images/<name> with PIL's pixels; returns max |diff| in 0..255.
int decode_diff(const std::string& name, bool print = true) {
  const Tensor want = decode_fixture().get("decoded/" + name);
  const Image img = load_image(fixture("images/" + name));
  EXPECT_EQ(want.dtype, DType::u8);
  EXPECT_EQ(img.height, want.dim(0)) << name;
  EXPECT_EQ(img.width, want.dim(1)) << name;
  EXPECT_EQ(3, want.dim(2)) << name;
  if (img.height != want.dim(0) || img.width != want.dim(1)) return 256;
  int max_diff = 0;
  int64_t differing = 0;
  const uint8_t* w = want.as<uint8_t>();
  for (std::size_t i = 0; i < img.rgb.size(); ++i) {
    const int d = std::abs(int(img.rgb[i]) - int(w[i]));
    max_diff = std::max(max_diff, d);
    differing += d != 0;
  }
  if (print)
    std::printf("  %-28s %4dx%-4d max|diff| %d (%lld of %zu samples differ)\n", name.c_str(),
                img.height, img.width, max_diff, (long long)differing, img.rgb.size());
  return max_diff;
}

std::vector<std::string> fixture_names(const std::string& ext) {
  std::vector<std::string> names;
  for (const auto& n : decode_fixture().names()) {
    const std::string file = n.substr(std::string("decoded/").size());
    if (file.size() > ext.size() && file.compare(file.size() - ext.size(), ext.size(), ext) == 0)
      names.push_back(file);
  }
  return names;
}

ErrorCode decode_error(const std::string& name, std::string* message) {
  try {
    load_image(fixture("bad/" + name));
  } catch (const Error& e) {
    *message = e.what();
    return e.code();
  }
  ADD_FAILURE() << name << " decoded without an error";
  return ErrorCode::internal;
}

}  // namespace

TEST(VisionDecode, PngMatchesPilExactly) {
  const auto names = fixture_names(".png");
  ASSERT_GE(names.size(),
            20u);  // every colour type, depth and interlacing variant the generator writes
  for (const auto& name : names) EXPECT_EQ(decode_diff(name), 0) << name;
}

TEST(VisionDecode, JpegMatchesPil) {
  // PIL wraps libjpeg-turbo with the same ISLOW IDCT and fancy upsampling: expected bit-exact.
  const auto names = fixture_names(".jpg");
  ASSERT_GE(names.size(), 9u);
  for (const auto& name : names) EXPECT_EQ(decode_diff(name), 0) << name;
}

TEST(VisionDecode, ExifOrientationIsIgnoredLikePil) {
  const Image img = load_image(fixture("images/exif_rotated.jpg"));
  // Stored 45 high x 61 wide with orientation 6; PIL (and so the policy) sees it unrotated.
  EXPECT_EQ(img.height, 45);
  EXPECT_EQ(img.width, 61);
}

TEST(VisionDecode, DecodeFromMemoryMatchesFile) {
  const auto bytes = read_bytes(fixture("images/q75_420.jpg"));
  const Image a = decode_image(bytes.data(), bytes.size(), "request.images.front");
  const Image b = load_image(fixture("images/q75_420.jpg"));
  EXPECT_EQ(a.rgb, b.rgb);
}

TEST(VisionDecode, CorruptAndTruncatedFilesAreFormatErrors) {
  for (const char* name : {"truncated.png", "truncated.jpg", "truncated_progressive.jpg",
                           "header_only.jpg", "signature_only.png", "bad_crc.png", "empty.png"}) {
    std::string msg;
    EXPECT_EQ(decode_error(name, &msg), ErrorCode::format) << name << ": " << msg;
    EXPECT_NE(msg.find(name), std::string::npos) << "message must name the file: " << msg;
  }
}

TEST(VisionDecode, UnsupportedFormatsAreRefused) {
  for (const char* name : {"cmyk.jpg", "not_an_image.gif", "random.bin"}) {
    std::string msg;
    EXPECT_EQ(decode_error(name, &msg), ErrorCode::unsupported) << name << ": " << msg;
    EXPECT_NE(msg.find(name), std::string::npos) << msg;
  }
}

TEST(VisionDecode, DecompressionBombsAreRefusedBeforeAllocation) {
  for (const char* name : {"bomb_400mp.png", "bomb_3600mp.jpg"}) {
    std::string msg;
    EXPECT_EQ(decode_error(name, &msg), ErrorCode::invalid_argument) << name << ": " << msg;
    EXPECT_NE(msg.find("over the limit"), std::string::npos) << msg;
  }
}

TEST(VisionDecode, EmptyBufferAndMissingFile) {
  try {
    decode_image(nullptr, 0, "request.images.wrist");
    FAIL() << "empty buffer decoded";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::format);
    EXPECT_NE(std::string(e.what()).find("request.images.wrist"), std::string::npos);
  }
  try {
    load_image(fixture("images/does_not_exist.png"));
    FAIL() << "missing file loaded";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::not_found);
    EXPECT_NE(std::string(e.what()).find("does_not_exist.png"), std::string::npos);
  }
}

TEST(VisionDecode, EveryTruncationOfAPngFails) {
  // No prefix of a PNG may decode to a silently partial image.
  const auto bytes = read_bytes(fixture("images/rgb8_interlaced.png"));
  for (std::size_t n = 0; n < bytes.size(); n += 97) {
    EXPECT_THROW(decode_image(bytes.data(), n, "prefix"), Error)
        << n << " of " << bytes.size() << " bytes";
  }
}

TEST(VisionDecode, RandomCorruptionOnlyEverThrowsTetherErrors) {
  // Deterministic byte flips, insertions and cuts: each input decodes or throws tether::Error,
  // never crashes or leaks another exception type (run under ASan/UBSan in the sanitizer build).
  uint64_t state = 0x9e3779b97f4a7c15ull;
  auto next = [&state] {
    state ^= state << 13;
    state ^= state >> 7;
    state ^= state << 17;
    return state;
  };
  int decoded = 0, refused = 0;
  for (const char* name : {"rgb8_interlaced.png", "palette4.png", "gray16.png", "q75_420.jpg",
                           "q75_420_progressive.jpg", "gray.jpg"}) {
    const auto original = read_bytes(fixture(std::string("images/") + name));
    for (int trial = 0; trial < 300; ++trial) {
      std::vector<uint8_t> bytes = original;
      const int edits = 1 + int(next() % 4);
      for (int e = 0; e < edits; ++e) {
        const std::size_t pos = next() % bytes.size();
        switch (next() % 3) {
          case 0:
            bytes[pos] ^= uint8_t(1 + next() % 255);
            break;
          case 1:
            bytes.insert(bytes.begin() + long(pos), uint8_t(next()));
            break;
          default:
            bytes.resize(std::max<std::size_t>(pos, 1));
            break;
        }
      }
      try {
        const Image img = decode_image(bytes.data(), bytes.size(), name);
        EXPECT_EQ(img.rgb.size(), std::size_t(img.height) * img.width * 3);
        ++decoded;
      } catch (const Error&) {
        ++refused;
      }
    }
  }
  std::printf("  corrupted inputs: %d decoded, %d refused\n", decoded, refused);
  EXPECT_GT(refused, 0);
}
