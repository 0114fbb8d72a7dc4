// Huge-page backed storage for packed weights (see huge_pages.h).
#include "backend/cpu/huge_pages.h"

#include <sys/mman.h>

#include <cstdint>
#include <cstdlib>
#include <new>

namespace tether::cpu {

namespace {
constexpr std::size_t kHugePage = std::size_t(2) << 20;
std::size_t round_up(std::size_t bytes, std::size_t to) { return (bytes + to - 1) / to * to; }
}  // namespace

void* huge_page_alloc(std::size_t bytes) {
  if (bytes < kHugePage) {
    void* p = std::aligned_alloc(64, round_up(bytes == 0 ? 1 : bytes, 64));
    if (!p) throw std::bad_alloc();
    return p;
  }
  // Map one huge page more than needed and unmap the unaligned head and the tail.
  const std::size_t size = round_up(bytes, kHugePage);
  void* raw = mmap(nullptr, size + kHugePage, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
  if (raw == MAP_FAILED) throw std::bad_alloc();
  const auto start = reinterpret_cast<std::uintptr_t>(raw);
  const std::uintptr_t aligned = round_up(start, kHugePage);
  if (aligned > start) munmap(raw, aligned - start);
  const std::size_t tail = start + size + kHugePage - (aligned + size);
  if (tail) munmap(reinterpret_cast<void*>(aligned + size), tail);
  void* p = reinterpret_cast<void*>(aligned);
#ifdef MADV_HUGEPAGE
  madvise(p, size, MADV_HUGEPAGE);  // advice only: without huge pages the mapping works as it is
#endif
  return p;
}

void huge_page_free(void* p, std::size_t bytes) noexcept {
  if (!p) return;
  if (bytes < kHugePage) std::free(p);
  else munmap(p, round_up(bytes, kHugePage));
}

}  // namespace tether::cpu
