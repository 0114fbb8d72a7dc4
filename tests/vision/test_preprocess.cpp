// SmolVLA image preprocessing parity (decode -> /255 -> resize_with_pad -> *2-1) against lerobot's
// own resize_with_pad run by torch, plus the building blocks and a timing of the 480x640 case.
#include <gtest/gtest.h>

#include <algorithm>

#include "core/error.h"
#include "vision/preprocess.h"
#include "vision_test_util.h"

using namespace tether;
using namespace tether::vision;
using namespace tether::vision::test;

namespace {

const SafeTensorsFile& preprocess_fixture() {
  static const SafeTensorsFile f = SafeTensorsFile::open(fixture("preprocess.safetensors"));
  return f;
}

Image image_from_tensor(const Tensor& t) {
  Image img;
  img.height = int(t.dim(0));
  img.width = int(t.dim(1));
  img.rgb.assign(t.as<uint8_t>(), t.as<uint8_t>() + t.numel());
  return img;
}

Image case_image(const SafeTensorsFile& f, const std::string& name, const std::string& source) {
  if (source.rfind("noise:", 0) == 0)
    return image_from_tensor(f.get("preprocess/" + name + "/image"));
  return load_image(fixture("images/" + source));  // the full path: our decoder feeds the resize
}

}  // namespace

TEST(VisionPreprocess, SmolvlaMatchesLerobotBitExactly) {
  const SafeTensorsFile& f = preprocess_fixture();
  const Json cases = metadata_json(f, "cases");
  ASSERT_GE(cases.size(), 8u);
  for (const auto& c : cases) {
    const std::string name = c["name"], source = c["source"];
    const int out_h = c["out"][0], out_w = c["out"][1];
    const Image img = case_image(f, name, source);
    for (const auto& [mode, threads] :
         {std::pair{"many", TorchThreads::many}, std::pair{"one", TorchThreads::one}}) {
      const std::string key = "preprocess/" + name + "/threads_" + mode;
      const Tensor want = f.get(f.contains(key) ? key : "preprocess/" + name + "/threads_many");
      ASSERT_EQ(want.shape, (Shape{3, out_h, out_w})) << key;
      std::vector<float> got(want.numel(), 42.0f);  // poison: every element must be written
      resize_with_pad_normalized(img, out_h, out_w, got.data(), threads);
      const Diff d = compare(got.data(), f32_values(want).data(), want.numel());
      std::printf("  %-28s %4dx%-4d -> %dx%d threads=%-4s max|diff| %.3g (%lld differ)\n",
                  name.c_str(), img.height, img.width, out_h, out_w, mode, d.max_abs,
                  (long long)d.mismatched);
      EXPECT_EQ(d.mismatched, 0) << key << " max|diff| " << d.max_abs;
    }
  }
}

TEST(VisionPreprocess, PortableKernelsGiveTheSameBits) {
  // CPUs without FMA run the portable build, where each fused multiply-add is a libm call.
  const Image img = load_image(fixture("images/camera_240x320.jpg"));
  for (const TorchThreads threads : {TorchThreads::many, TorchThreads::one}) {
    std::vector<float> fast(3 * 200 * 200), portable(3 * 200 * 200);
    resize_with_pad_normalized(img, 200, 200, fast.data(), threads);
    detail::force_portable_kernels(true);
    resize_with_pad_normalized(img, 200, 200, portable.data(), threads);
    detail::force_portable_kernels(false);
    const Diff d = compare(portable.data(), fast.data(), int64_t(fast.size()));
    EXPECT_EQ(d.mismatched, 0) << "max|diff| " << d.max_abs;
  }
}

TEST(VisionPreprocess, SidesThatWouldVanishAreRefusedLikeTorch) {
  const Json errors = metadata_json(preprocess_fixture(), "errors");
  ASSERT_GE(errors.size(), 1u);
  for (const auto& e : errors) {
    Image img;
    img.height = e["in"][0];
    img.width = e["in"][1];
    img.rgb.assign(std::size_t(img.height) * img.width * 3, 7);
    std::vector<float> out(3 * int(e["out"][0]) * int(e["out"][1]));
    try {
      resize_with_pad_normalized(img, e["out"][0], e["out"][1], out.data());
      ADD_FAILURE() << e["name"] << " was accepted; torch said: " << e["torch_error"];
    } catch (const Error& err) {
      EXPECT_EQ(err.code(), ErrorCode::invalid_argument);
    }
  }
}

TEST(VisionPreprocess, BuildingBlocksComposeToTheSameResult) {
  // to_float_chw + resize_with_pad(pad 0) + (x*2-1) must equal the fused uint8 path bit for bit.
  const Image img = load_image(fixture("images/camera_240x320.jpg"));
  const int oh = 100, ow = 150;
  std::vector<float> chw(3 * img.height * img.width), padded(3 * oh * ow), fused(3 * oh * ow);
  to_float_chw(img, chw.data());
  EXPECT_EQ(chw[0], float(img.rgb[0]) / 255.0f);
  EXPECT_EQ(chw[img.height * img.width], float(img.rgb[1]) / 255.0f);
  resize_with_pad(chw.data(), 3, img.height, img.width, oh, ow, 0.0f, padded.data());
  for (float& v : padded) v = v * 2.0f - 1.0f;
  resize_with_pad_normalized(img, oh, ow, fused.data());
  const Diff d = compare(fused.data(), padded.data(), int64_t(fused.size()));
  EXPECT_EQ(d.mismatched, 0) << "max|diff| " << d.max_abs;
  // 240x320 into 100x150: ratio 2.4 -> 100x133, so 17 padded columns on the left at exactly -1.
  EXPECT_EQ(fused[0], -1.0f);
  EXPECT_EQ(fused[16], -1.0f);
  EXPECT_NE(fused[17], -1.0f);
}

TEST(VisionPreprocess, InvalidImagesThrow) {
  Image bad;
  bad.height = 4;
  bad.width = 4;
  bad.rgb.resize(10);  // not 4x4x3
  std::vector<float> out(3 * 8 * 8);
  EXPECT_THROW(resize_with_pad_normalized(bad, 8, 8, out.data()), Error);
  Image empty;
  EXPECT_THROW(resize_with_pad_normalized(empty, 8, 8, out.data()), Error);
  Image ok;
  ok.height = ok.width = 2;
  ok.rgb.assign(12, 1);
  EXPECT_THROW(resize_with_pad_normalized(ok, 0, 8, out.data()), Error);
  EXPECT_THROW(resize_with_pad_normalized(ok, 8, 8, nullptr), Error);
}
