// The CUDA backend's cached device allocator (see device_pool.h). Host logic only: it is built and tested in every
// build, with or without CUDA.
#include "backend/cuda/device_pool.h"

#include <algorithm>

namespace tether::cuda {

struct DevicePool::State {
  RawAllocate raw_allocate;
  RawFree raw_free;
  mutable std::mutex mutex;
  std::multimap<std::size_t, void*> free_blocks;  // size class -> cached block
  Stats stats;
  bool closed = false;  // the pool is gone: blocks coming back go straight to the device

  void give_back(void* p, std::size_t size) {
    std::lock_guard lock(mutex);
    stats.in_use -= size;
    if (closed) {
      raw_free(p);
      return;
    }
    free_blocks.emplace(size, p);
    stats.cached += size;
  }
  void free_cached_locked() {
    for (auto& [size, p] : free_blocks) raw_free(p);
    free_blocks.clear();
    stats.cached = 0;
  }
};

DevicePool::DevicePool(RawAllocate raw_allocate, RawFree raw_free) : state_(std::make_shared<State>()) {
  state_->raw_allocate = std::move(raw_allocate);
  state_->raw_free = std::move(raw_free);
}

DevicePool::~DevicePool() {
  std::lock_guard lock(state_->mutex);
  state_->free_cached_locked();
  state_->closed = true;
}

std::size_t DevicePool::size_class(std::size_t bytes) {
  constexpr std::size_t kSmallStep = 512, kLargeStep = std::size_t(2) << 20, kSmallLimit = std::size_t(1) << 20;
  bytes = std::max<std::size_t>(bytes, 1);
  if (bytes <= kSmallLimit) return (bytes + kSmallStep - 1) / kSmallStep * kSmallStep;
  return (bytes + kLargeStep - 1) / kLargeStep * kLargeStep;
}

std::shared_ptr<void> DevicePool::allocate(std::size_t bytes) {
  const std::size_t size = size_class(bytes);
  void* p = nullptr;
  {
    std::lock_guard lock(state_->mutex);
    Stats& s = state_->stats;
    if (auto it = state_->free_blocks.find(size); it != state_->free_blocks.end()) {
      p = it->second;
      state_->free_blocks.erase(it);
      s.cached -= size;
    } else {
      p = state_->raw_allocate(size);
      if (!p && !state_->free_blocks.empty()) {
        // Cached blocks of other sizes may be what stands in the way.
        state_->free_cached_locked();
        p = state_->raw_allocate(size);
      }
      if (!p) return nullptr;
      ++s.device_allocations;
    }
    s.in_use += size;
    s.peak = std::max(s.peak, s.in_use + s.cached);
  }
  std::shared_ptr<State> state = state_;
  return std::shared_ptr<void>(p, [state, size](void* q) { state->give_back(q, size); });
}

DevicePool::Stats DevicePool::stats() const {
  std::lock_guard lock(state_->mutex);
  return state_->stats;
}

void DevicePool::trim() {
  std::lock_guard lock(state_->mutex);
  state_->free_cached_locked();
}

}  // namespace tether::cuda
