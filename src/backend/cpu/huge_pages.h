// Storage for packed weights on transparent huge pages. Every forward streams the packed weights from memory; on
// 4 KB pages each 32 KB panel block spans eight pages and every page costs a TLB miss (a two-dimensional page walk
// inside a VM). On 2 MB pages one entry covers 64 blocks. Internal to the CPU backend.
#pragma once

#include <cstddef>
#include <vector>

namespace tether::cpu {

// Allocations of at least 2 MB are 2 MB-aligned mappings marked MADV_HUGEPAGE before their first touch, so the kernel
// backs them with huge pages when transparent huge pages are "madvise" or "always" (under "never", or where huge
// pages are unavailable, they are ordinary pages). Smaller ones come from the heap, 64-byte aligned.
void* huge_page_alloc(std::size_t bytes);
void huge_page_free(void* p, std::size_t bytes) noexcept;

template <class T>
struct HugePageAllocator {
  using value_type = T;
  HugePageAllocator() = default;
  template <class U>
  HugePageAllocator(const HugePageAllocator<U>&) noexcept {}
  T* allocate(std::size_t n) { return static_cast<T*>(huge_page_alloc(n * sizeof(T))); }
  void deallocate(T* p, std::size_t n) noexcept { huge_page_free(p, n * sizeof(T)); }
  template <class U>
  bool operator==(const HugePageAllocator<U>&) const noexcept { return true; }
};

// Packed weight panels.
template <class T>
using PanelBuffer = std::vector<T, HugePageAllocator<T>>;

}  // namespace tether::cpu
