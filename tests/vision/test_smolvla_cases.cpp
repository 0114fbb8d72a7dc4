// Cross-check against the SmolVLA oracle fixtures (tests/fixtures/smolvla/<case>/): the camera
// files fed to the real upstream policy must decode to its input pixels, and resize_with_pad_normalized
// must reproduce what the policy's own prepare_images produced ("pre.pixels.<camera>").
#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>

#include "vision/preprocess.h"
#include "vision_test_util.h"

using namespace tether;
using namespace tether::vision;
using namespace tether::vision::test;
namespace fs = std::filesystem;

TEST(VisionSmolvlaOracle, CameraFilesDecodeAndPreprocessLikeThePolicy) {
  const fs::path root = fs::path(TETHER_FIXTURES_DIR) / "smolvla";
  int checked = 0;
  for (const auto& entry : fs::directory_iterator(root)) {
    const fs::path oracle_path = entry.path() / "oracle.safetensors";
    if (!fs::exists(oracle_path)) continue;
    const std::string case_name = entry.path().filename().string();
    const SafeTensorsFile oracle = SafeTensorsFile::open(oracle_path.string());
    const Json files = Json::parse(oracle.metadata().at("input_files"));
    // SmolVLA stores the target as (width, height).
    const Json config = read_json_file((entry.path() / "checkpoint" / "config.json").string());
    const int out_w = config.at("resize_imgs_with_padding")[0],
              out_h = config.at("resize_imgs_with_padding")[1];
    for (const auto& [camera, names] : files.items()) {
      const Tensor pixels_in = oracle.get("input.image." + camera);
      const Tensor pixels_out = oracle.get("pre.pixels." + camera);
      ASSERT_EQ(pixels_out.dtype, DType::f32);
      const std::vector<float> want = f32_values(pixels_out);  // aligned copy of the file's bytes
      for (std::size_t b = 0; b < names.size(); ++b) {
        const std::string file = (entry.path() / "inputs" / names[b].get<std::string>()).string();
        const Image img = load_image(file);
        ASSERT_EQ(img.height, pixels_in.dim(1)) << file;
        ASSERT_EQ(img.width, pixels_in.dim(2)) << file;
        const std::size_t n = img.rgb.size();
        EXPECT_EQ(0, std::memcmp(img.rgb.data(), pixels_in.as<uint8_t>() + b * n, n))
            << file << " decodes differently";

        const int64_t m = 3LL * out_h * out_w;
        ASSERT_EQ(pixels_out.numel(), m * int64_t(names.size()));
        std::vector<float> got(m);
        resize_with_pad_normalized(img, out_h, out_w, got.data());
        const Diff d = compare(got.data(), want.data() + b * m, m);
        std::printf("  %-32s %-28s %3dx%-3d -> %dx%d max|diff| %.3g\n", case_name.c_str(),
                    camera.c_str(), img.height, img.width, out_h, out_w, d.max_abs);
        EXPECT_EQ(d.mismatched, 0) << file << " max|diff| " << d.max_abs;
        ++checked;
      }
    }
  }
  ASSERT_GT(checked, 0) << "no SmolVLA oracle cases found under " << root;
}
