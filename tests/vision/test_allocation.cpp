// resize_with_pad_normalized runs per request: once a thread has warmed up for a size, it must not
// allocate. Counted by replacing the global operator new in this test binary (skipped under ASan,
// which supplies its own).
#include <gtest/gtest.h>

#include <atomic>
#include <cstdlib>
#include <memory>
#include <new>

#include "vision/preprocess.h"
#include "vision_test_util.h"

#if !defined(__SANITIZE_ADDRESS__)
namespace {
std::atomic<long> g_allocations{0};
}

void* operator new(std::size_t n) {
  g_allocations.fetch_add(1, std::memory_order_relaxed);
  if (void* p = std::malloc(n ? n : 1)) return p;
  throw std::bad_alloc();
}
void operator delete(void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }

TEST(VisionAllocation, PreprocessIsAllocationFreeOnceWarm) {
  using namespace tether::vision;
  const Image img = load_image(test::fixture("images/camera_240x320.jpg"));
  std::vector<float> out(3 * 512 * 512), small(3 * 64 * 96);
  resize_with_pad_normalized(img, 512, 512, out.data());  // warm-up: per-thread index tables grow once
  const long before = g_allocations.load();
  for (int i = 0; i < 5; ++i) {
    resize_with_pad_normalized(img, 512, 512, out.data());
    resize_with_pad_normalized(img, 64, 96, small.data(), TorchThreads::one);  // smaller: reuses the tables
  }
  EXPECT_EQ(g_allocations.load() - before, 0);
  // The counter is live: a plain heap allocation is seen.
  auto probe = std::make_unique<int>(1);
  EXPECT_EQ(g_allocations.load() - before, 1);
}
#endif
