// The CUDA backend's device memory plan (src/backend/cuda/device_pool.h) over a fake device: blocks come back and are
// reused, so a second pass over the same shapes allocates nothing; a full device is retried after the cache is freed.
#include <gtest/gtest.h>

#include <cstdlib>
#include <map>
#include <set>
#include <vector>

#include "backend/cuda/device_pool.h"

namespace tether::cuda {
namespace {

struct FakeDevice {
  std::size_t capacity = std::size_t(64) << 20, used = 0;
  std::set<void*> live;
  int allocations = 0, frees = 0;
  DevicePool::RawAllocate allocate() {
    return [this](std::size_t bytes) -> void* {
      if (used + bytes > capacity) return nullptr;
      used += bytes;
      ++allocations;
      void* p = std::malloc(bytes);
      live.insert(p);
      sizes[p] = bytes;
      return p;
    };
  }
  DevicePool::RawFree release() {
    return [this](void* p) {
      used -= sizes[p];
      live.erase(p);
      ++frees;
      std::free(p);
    };
  }
  std::map<void*, std::size_t> sizes;
};

TEST(DevicePool, SizeClasses) {
  EXPECT_EQ(DevicePool::size_class(0), 512u);
  EXPECT_EQ(DevicePool::size_class(1), 512u);
  EXPECT_EQ(DevicePool::size_class(513), 1024u);
  EXPECT_EQ(DevicePool::size_class(std::size_t(1) << 20), std::size_t(1) << 20);
  EXPECT_EQ(DevicePool::size_class((std::size_t(1) << 20) + 1), std::size_t(2) << 20);
  EXPECT_EQ(DevicePool::size_class((std::size_t(5) << 20) + 7), std::size_t(6) << 20);
}

TEST(DevicePool, ASecondPassOverTheSameShapesAllocatesNothing) {
  FakeDevice device;
  DevicePool pool(device.allocate(), device.release());
  const std::size_t shapes[] = {4000, 300000, std::size_t(3) << 20, 4000, 70};
  for (int pass = 0; pass < 3; ++pass) {
    std::vector<std::shared_ptr<void>> held;
    for (std::size_t bytes : shapes) {
      held.push_back(pool.allocate(bytes));
      ASSERT_TRUE(held.back());
    }
    if (pass == 0) {
      EXPECT_EQ(device.allocations, 5);
    }
  }
  EXPECT_EQ(device.allocations, 5) << "later passes reused the cached blocks";
  const auto s = pool.stats();
  EXPECT_EQ(s.in_use, 0u);
  EXPECT_EQ(s.device_allocations, 5u);
  EXPECT_EQ(s.cached, s.peak);
  pool.trim();
  EXPECT_EQ(device.used, 0u);
}

TEST(DevicePool, AFullDeviceIsRetriedAfterTheCacheIsFreed) {
  FakeDevice device;
  device.capacity = std::size_t(10) << 20;
  DevicePool pool(device.allocate(), device.release());
  { auto a = pool.allocate(std::size_t(6) << 20); }  // cached after use
  auto b = pool.allocate(std::size_t(8) << 20);         // does not fit beside the cached block
  ASSERT_TRUE(b);
  EXPECT_EQ(pool.stats().cached, 0u);
  EXPECT_FALSE(pool.allocate(std::size_t(4) << 20)) << "no room even after trimming: null, the caller reports it";
}

TEST(DevicePool, BlocksOutlivingThePoolGoBackToTheDevice) {
  FakeDevice device;
  std::shared_ptr<void> survivor;
  {
    DevicePool pool(device.allocate(), device.release());
    survivor = pool.allocate(1000);
    auto cached = pool.allocate(2000);
  }
  EXPECT_EQ(device.live.size(), 1u);
  survivor.reset();
  EXPECT_TRUE(device.live.empty());
}

}  // namespace
}  // namespace tether::cuda
