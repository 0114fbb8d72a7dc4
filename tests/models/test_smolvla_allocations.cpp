// The denoise loop must not allocate: a warmed predict allocates the same amount whatever the step count.
// Allocations made inside oneDNN's sgemm (a few hundred bytes of per-call bookkeeping, freed at once) are the
// GEMM library's own and are not counted; every buffer Tether uses is planned once per shape.
#include <dlfcn.h>
#include <execinfo.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <atomic>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <new>

#include "models/family.h"
#include "vision/image.h"
#include "scratch_dir.h"

// The replacement operator new/delete pair below uses malloc/free; GCC cannot see that they match.
#pragma GCC diagnostic ignored "-Wmismatched-new-delete"

namespace {
std::atomic<long> g_allocations{0};

// True when one of the nearest callers lives in oneDNN (directly, or through a libstdc++ helper it called).
bool called_from_gemm_library() {
  void* frames[8];
  const int n = backtrace(frames, 8);
  for (int i = 1; i < n; ++i) {
    Dl_info info{};
    if (dladdr(frames[i], &info) && info.dli_fname && std::strstr(info.dli_fname, "libdnnl")) return true;
  }
  return false;
}
}  // namespace

void* operator new(std::size_t n) {
  // backtrace() may allocate the first time it runs; guard against counting (or recursing into) ourselves.
  static thread_local bool inside = false;
  if (!inside) {
    inside = true;
    if (!called_from_gemm_library()) g_allocations.fetch_add(1, std::memory_order_relaxed);
    inside = false;
  }
  if (void* p = std::malloc(n ? n : 1)) return p;
  throw std::bad_alloc();
}
void operator delete(void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }

using namespace tether;
namespace fs = std::filesystem;

namespace {

// A copy of a fixture checkpoint with `num_steps` changed.
fs::path checkpoint_with_steps(int steps) {
  const fs::path src = fs::path(TETHER_FIXTURES_DIR) / "smolvla" / "cam1_stats" / "checkpoint";
  const fs::path dst =
      tether::testing::scratch_dir() / ("steps_" + std::to_string(steps));
  fs::remove_all(dst);
  fs::copy(src, dst, fs::copy_options::recursive);
  Json config = read_json_file((dst / "config.json").string());
  config["num_steps"] = steps;
  std::ofstream(dst / "config.json") << config.dump(2);
  return dst;
}

long allocations_of_warm_predict(int steps) {
  const fs::path dir = checkpoint_with_steps(steps);
  auto model = models::load_checkpoint(dir).model;
  models::ModelInput in;
  in.images["observation.images.camera1"] =
      vision::load_image((fs::path(TETHER_FIXTURES_DIR) / "smolvla/cam1_stats/inputs/camera1_0.png").string());
  in.state.assign(6, 0.25f);
  in.instruction = "stack the blocks";
  in.seed = 5;
  const std::vector<models::ModelInput> batch = {in, in};
  model->predict(batch);  // plans buffers for this shape
  model->predict(batch);
  const long before = g_allocations.load();
  model->predict(batch);
  const long used = g_allocations.load() - before;
  fs::remove_all(dir);
  return used;
}

}  // namespace

TEST(SmolVLAAllocations, DenoiseStepsDoNotAllocate) {
  const long two = allocations_of_warm_predict(2);
  const long eight = allocations_of_warm_predict(8);
  std::printf("[ allocs     ] warm predict: %ld allocations with 2 steps, %ld with 8 steps\n", two, eight);
  // Six more steps must not bring six more allocations. The count can still differ by one or two: a kernel's
  // thread-local scratch is sized the first time an OpenMP thread runs it, and which thread runs which task
  // depends on scheduling.
  EXPECT_LT(std::labs(eight - two), 6) << "the denoise loop allocates";
  EXPECT_GT(two, 0) << "the counter is not counting";
}
