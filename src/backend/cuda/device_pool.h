// Device memory for the CUDA backend, cached: a block given back is kept and handed out again for a request of the
// same size class, so once a model has run each (batch, prefix) shape, serving allocates nothing. Plain C++ over two
// functions (allocate, free), so the plan is unit-tested without a GPU.
#pragma once

#include <cstddef>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <vector>

namespace tether::cuda {

class DevicePool {
 public:
  // raw_allocate returns null when the device is out of memory; raw_free gives a block back to the device.
  using RawAllocate = std::function<void*(std::size_t bytes)>;
  using RawFree = std::function<void(void*)>;
  DevicePool(RawAllocate raw_allocate, RawFree raw_free);
  ~DevicePool();  // frees what is cached; blocks still handed out are freed when their last owner lets go
  DevicePool(const DevicePool&) = delete;
  DevicePool& operator=(const DevicePool&) = delete;

  // A block of at least `bytes` (256-byte aligned, as cudaMalloc's), given back to the pool when the last copy of the
  // pointer goes. Reuses a cached block of the same size class before asking the device; when the device refuses,
  // frees the whole cache and asks once more; returns null if that fails too.
  std::shared_ptr<void> allocate(std::size_t bytes);

  // The size class a request is rounded to: 512-byte steps up to 1 MiB, then 2 MiB steps (large activations and
  // weights, whose exact size recurs).
  static std::size_t size_class(std::size_t bytes);

  struct Stats {
    std::size_t in_use = 0;         // bytes handed out now
    std::size_t cached = 0;         // bytes kept for reuse
    std::size_t peak = 0;           // most bytes ever held from the device (in use + cached)
    std::size_t device_allocations = 0;  // raw allocations made since the pool was made
  };
  Stats stats() const;
  // Frees every cached block (the device gets their memory back); blocks in use stay.
  void trim();

 private:
  struct State;
  std::shared_ptr<State> state_;
};

}  // namespace tether::cuda
