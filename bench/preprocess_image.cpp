// Times image preprocessing (decode excluded): a 480x640 camera frame resized with padding into SmolVLA's
// 512x512 input and into the test fixtures' 128x128. Median and minimum of 30 runs after one warm-up.
// Usage: build/release/bench/preprocess_image [IMAGE]   (default: tests/fixtures/vision/images/scene_480x640.png)
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <exception>
#include <string>
#include <vector>

#include "vision/image.h"
#include "vision/preprocess.h"

int main(int argc, char** argv) try {
  const std::string path = argc > 1 ? argv[1] : std::string(TETHER_SOURCE_DIR_BENCH) +
                                                     "/tests/fixtures/vision/images/scene_480x640.png";
  const tether::vision::Image img = tether::vision::load_image(path);
  for (const int side : {512, 128}) {
    std::vector<float> out(std::size_t(3) * side * side);
    tether::vision::resize_with_pad_normalized(img, side, side, out.data());  // warm-up: index tables reach their size
    std::vector<double> ms;
    for (int i = 0; i < 30; ++i) {
      const auto t0 = std::chrono::steady_clock::now();
      tether::vision::resize_with_pad_normalized(img, side, side, out.data());
      ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
    }
    std::sort(ms.begin(), ms.end());
    std::printf("preprocess %dx%d -> %dx%d: median %.3f ms, min %.3f ms\n", img.height, img.width, side, side,
                ms[15], ms[0]);
  }
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "error: %s\n", e.what());
  return 2;
}
