// torch bilinear parity: resize_bilinear against F.interpolate outputs for both of torch's float
// kernels (several threads / one thread), on up, down, odd, identity and one-pixel cases.
#include <gtest/gtest.h>

#include <cstdio>

#include "core/error.h"
#include "vision/preprocess.h"
#include "vision_test_util.h"

using namespace tether;
using namespace tether::vision;
using namespace tether::vision::test;

namespace {

const SafeTensorsFile& resize_fixture() {
  static const SafeTensorsFile f = SafeTensorsFile::open(fixture("resize.safetensors"));
  return f;
}

}  // namespace

TEST(VisionResize, BilinearMatchesTorchBitExactly) {
  const SafeTensorsFile& f = resize_fixture();
  const Json cases = metadata_json(f, "cases");
  ASSERT_GE(cases.size(), 10u);
  int differing_cases = 0;
  for (const auto& c : cases) {
    const std::string name = c["name"];
    const int ch = c["channels"], in_h = c["in"][0], in_w = c["in"][1], out_h = c["out"][0],
              out_w = c["out"][1];
    const Tensor input = f.get("resize/" + name + "/input");
    ASSERT_EQ(input.shape, (Shape{ch, in_h, in_w})) << name;
    const std::vector<float> input_f32 =
        f32_values(input);  // aligned copy: views into the file may not be
    differing_cases += bool(c["threads_differ"]);
    for (const auto& [mode, threads] :
         {std::pair{"many", TorchThreads::many}, std::pair{"one", TorchThreads::one}}) {
      // Only stored where torch's single-thread kernel rounds differently from the multi-thread
      // one.
      const std::string key = "resize/" + name + "/threads_" + mode;
      const Tensor want = f.get(f.contains(key) ? key : "resize/" + name + "/threads_many");
      ASSERT_EQ(want.shape, (Shape{ch, out_h, out_w})) << key;
      std::vector<float> got(want.numel());
      resize_bilinear(input_f32.data(), ch, in_h, in_w, out_h, out_w, got.data(), threads);
      const Diff d = compare(got.data(), f32_values(want).data(), want.numel());
      const char* kernel =
          torch_bilinear_kernel(ch, in_h, in_w, out_h, out_w, threads) == BilinearKernel::separable
              ? "separable"
              : "four-tap";
      std::printf("  %-30s threads=%-4s %-9s max|diff| %.3g (%lld differ)\n", name.c_str(), mode,
                  kernel, d.max_abs, (long long)d.mismatched);
      EXPECT_EQ(d.mismatched, 0) << key << " max|diff| " << d.max_abs;
    }
  }
  // The fixture must actually separate the two kernels, or the thread switch is untested.
  EXPECT_GE(differing_cases, 2);
}

TEST(VisionResize, KernelChoiceFollowsTorch) {
  EXPECT_EQ(torch_bilinear_kernel(3, 480, 640, 384, 512, TorchThreads::many),
            BilinearKernel::separable);
  EXPECT_EQ(torch_bilinear_kernel(3, 480, 640, 384, 512, TorchThreads::one),
            BilinearKernel::four_tap);
  EXPECT_EQ(torch_bilinear_kernel(1, 480, 640, 384, 512, TorchThreads::one),
            BilinearKernel::separable);
  EXPECT_EQ(torch_bilinear_kernel(3, 96, 128, 48, 64, TorchThreads::many),
            BilinearKernel::four_tap);  // 48+64 <= 128
  EXPECT_EQ(torch_bilinear_kernel(3, 96, 128, 64, 65, TorchThreads::many),
            BilinearKernel::separable);
  EXPECT_EQ(torch_bilinear_kernel(8, 1, 1, 100, 100, TorchThreads::many), BilinearKernel::four_tap);
}

TEST(VisionResize, InvalidArgumentsThrow) {
  std::vector<float> in(12, 0.5f), out(64);
  EXPECT_THROW(resize_bilinear(in.data(), 3, 2, 2, 0, 4, out.data()), Error);
  EXPECT_THROW(resize_bilinear(in.data(), 3, 0, 2, 4, 4, out.data()), Error);
  EXPECT_THROW(resize_bilinear(in.data(), 0, 2, 2, 4, 4, out.data()), Error);
  EXPECT_THROW(resize_bilinear(nullptr, 3, 2, 2, 4, 4, out.data()), Error);
  EXPECT_THROW(resize_bilinear(in.data(), 3, 2, 2, 4, 4, nullptr), Error);
}

TEST(VisionResize, ResizeWithPadPadsLeftAndTop) {
  // 2x4 -> 4x4: ratio 1, no resampling (torch's same-size kernel copies), 2 rows of padding on top.
  std::vector<float> in = {1, 2, 3, 4, 5, 6, 7, 8};
  std::vector<float> out(16, 123.0f);
  resize_with_pad(in.data(), 1, 2, 4, 4, 4, -7.0f, out.data());
  const std::vector<float> want = {-7, -7, -7, -7, -7, -7, -7, -7, 1, 2, 3, 4, 5, 6, 7, 8};
  EXPECT_EQ(out, want);
  // 4x2 -> 4x4: padding on the left.
  std::vector<float> out2(16);
  resize_with_pad(in.data(), 1, 4, 2, 4, 4, 0.0f, out2.data());
  const std::vector<float> want2 = {0, 0, 1, 2, 0, 0, 3, 4, 0, 0, 5, 6, 0, 0, 7, 8};
  EXPECT_EQ(out2, want2);
}

TEST(VisionResize, ResizeWithPadSizeIsPythonArithmetic) {
  EXPECT_EQ(resize_with_pad_size(480, 640, 512, 512).height, 384);
  EXPECT_EQ(resize_with_pad_size(480, 640, 512, 512).width, 512);
  EXPECT_EQ(resize_with_pad_size(120, 80, 64, 64).width, 42);  // 80 / 1.875 = 42.67, truncated
  EXPECT_EQ(resize_with_pad_size(40, 1, 64, 64).width, 1);
  EXPECT_THROW(resize_with_pad_size(1, 1000, 64, 64), Error);  // the height would be 0 pixels
}
