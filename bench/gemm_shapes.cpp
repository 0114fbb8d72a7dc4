// Times a family's full-size GEMM shapes (y[M,N] = x[M,K] W[N,K]^T; SmolVLA's by default, pi0's with --model pi0)
// on every candidate: OpenBLAS, oneDNN matmul
// (f32, native bf16 where the CPU has it), Tether's panel GEMM with f32 / bf16 / fp16 weights widened in the kernel,
// and bf16 weights widened to an f32 copy before each oneDNN call. Chooses the library and the half-precision path
// on CPUs without bf16 instructions; prints the machine's best measured fp32 GEMM rate. Results: bench/GEMM.md.
#include <cblas.h>
#include <omp.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <functional>
#include <oneapi/dnnl/dnnl.hpp>
#include <random>
#include <string>
#include <vector>

#include "backend/cpu/cpu_features.h"
#include "backend/cpu/gemm.h"
#include "backend/cpu/panel_gemm.h"
#include "core/dtype.h"

namespace {

struct GemmShape {
  const char* group;
  const char* name;
  int64_t m, n, k;
  // Calls per inference (SmolVLA: 3 cameras, 12 SigLIP layers per image, 16 VLM layers, 16 expert layers of which 8
  // cross-attend, 10 denoising steps; pi0: 1 camera, 27 SigLIP layers, 18 VLM layers, 18 expert layers, 10 steps);
  // 0 marks an alternative length, not counted.
  int calls;
};

// Prefix of 3 images x 64 tokens + text + state is about 241 tokens; 113 is the 1-camera case.
const GemmShape kShapes[] = {
    {"vision", "qkv 768->768", 1024, 768, 768, 3 * 12 * 3},
    {"vision", "out 768->768", 1024, 768, 768, 12 * 3},
    {"vision", "fc1 768->3072", 1024, 3072, 768, 12 * 3},
    {"vision", "fc2 3072->768", 1024, 768, 3072, 12 * 3},
    {"vision", "patch 768->768", 1024, 768, 768, 3},
    {"connector", "12288->960", 64, 960, 12288, 3},
    {"prefix241", "q 960->960", 241, 960, 960, 16},
    {"prefix241", "k/v 960->320", 241, 320, 960, 2 * 16},
    {"prefix241", "o 960->960", 241, 960, 960, 16},
    {"prefix241", "gate/up 960->2560", 241, 2560, 960, 2 * 16},
    {"prefix241", "down 2560->960", 241, 960, 2560, 16},
    {"prefix113", "q 960->960", 113, 960, 960, 0},
    {"prefix113", "k/v 960->320", 113, 320, 960, 0},
    {"prefix113", "o 960->960", 113, 960, 960, 0},
    {"prefix113", "gate/up 960->2560", 113, 2560, 960, 0},
    {"prefix113", "down 2560->960", 113, 960, 2560, 0},
    {"expert", "q 720->960", 50, 960, 720, 16 * 10},
    {"expert", "k/v 720->320", 50, 320, 720, 2 * 8 * 10},
    {"expert", "cross k/v 320->320 (M=241)", 241, 320, 320, 2 * 8 * 10},
    {"expert", "o 960->720", 50, 720, 960, 16 * 10},
    {"expert", "gate/up 720->2048", 50, 2048, 720, 2 * 16 * 10},
    {"expert", "down 2048->720", 50, 720, 2048, 16 * 10},
    {"expert", "action_in 32->720", 50, 720, 32, 10},
    {"expert", "time_mlp_in 1440->720", 50, 720, 1440, 10},
    {"expert", "time_mlp_out 720->720", 50, 720, 720, 10},
    {"expert", "action_out 720->32", 50, 32, 720, 10},
};

// pi0 / pi0.5 with one 224 px camera: SigLIP so400m over 256 patches, a prefix of 256 image + ~14 text tokens
// through Gemma 2B (q, k, v and gate, up stacked as Tether runs them; the last layer computes only its K/V), and
// the Gemma 300M expert over the 50 action tokens (pi0's state token once per request is left out).
const GemmShape kPi0Shapes[] = {
    {"vision", "qkv 1152->3456", 256, 3456, 1152, 27},
    {"vision", "out 1152->1152", 256, 1152, 1152, 27},
    {"vision", "fc1 1152->4304", 256, 4304, 1152, 27},
    {"vision", "fc2 4304->1152", 256, 1152, 4304, 27},
    {"projector", "1152->2048", 256, 2048, 1152, 1},
    {"prefix270", "qkv 2048->2560", 270, 2560, 2048, 17},
    {"prefix270", "k/v 2048->512 (last layer)", 270, 512, 2048, 1},
    {"prefix270", "o 2048->2048", 270, 2048, 2048, 17},
    {"prefix270", "gate/up 2048->32768", 270, 32768, 2048, 17},
    {"prefix270", "down 16384->2048", 270, 2048, 16384, 17},
    {"expert", "qkv 1024->2560", 50, 2560, 1024, 18 * 10},
    {"expert", "o 2048->1024", 50, 1024, 2048, 18 * 10},
    {"expert", "gate/up 1024->8192", 50, 8192, 1024, 18 * 10},
    {"expert", "down 4096->1024", 50, 1024, 4096, 18 * 10},
    {"expert", "action_time_mlp_in 2048->1024", 50, 1024, 2048, 10},
    {"expert", "action_time_mlp_out 1024->1024", 50, 1024, 1024, 10},
};

// GR00T N1.7, as bench/gr00t_cpu.sh runs it: 1 camera, a 640 x 480 frame (models/demo/sample.png) cropped and resized
// to 352 x 256 (a 22 x 16 patch grid: 352 patches, 88 image tokens) and a prompt of 109 tokens, which the VL
// self-attention and the DiT's cross-attention K/V also see; 4 denoising steps over 41 DiT tokens (the state and 40
// actions).
const GemmShape kGr00tN17Shapes[] = {
    {"vision", "patch 1536->1024", 352, 1024, 1536, 1},
    {"vision", "qkv 1024->3072", 352, 3072, 1024, 24},
    {"vision", "proj 1024->1024", 352, 1024, 1024, 24},
    {"vision", "fc1 1024->4096", 352, 4096, 1024, 24},
    {"vision", "fc2 4096->1024", 352, 1024, 4096, 24},
    {"vision", "merger fc1 4096->4096", 88, 4096, 4096, 4},
    {"vision", "merger fc2 4096->2048", 88, 2048, 4096, 4},
    {"text109", "q|k|v 2048->4096", 109, 4096, 2048, 16},
    {"text109", "o 2048->2048", 109, 2048, 2048, 16},
    {"text109", "gate/up 2048->12288", 109, 12288, 2048, 16},
    {"text109", "down 6144->2048", 109, 2048, 6144, 16},
    {"vl_attn109", "qkv 2048->6144", 109, 6144, 2048, 4},
    {"vl_attn109", "out 2048->2048", 109, 2048, 2048, 4},
    {"vl_attn109", "ff1 2048->8192", 109, 8192, 2048, 4},
    {"vl_attn109", "ff2 8192->2048", 109, 2048, 8192, 4},
    {"dit", "cross k|v 2048->3072 (M=109)", 109, 3072, 2048, 16},
    {"dit", "cross q 1536->1536", 41, 1536, 1536, 16 * 4},
    {"dit", "self qkv 1536->4608", 41, 4608, 1536, 16 * 4},
    {"dit", "out 1536->1536", 41, 1536, 1536, 32 * 4},
    {"dit", "ff1 1536->6144", 41, 6144, 1536, 32 * 4},
    {"dit", "ff2 6144->1536", 41, 1536, 6144, 32 * 4},
    {"head", "action W2 3072->1536", 40, 1536, 3072, 4},
    {"head", "action W3 1536->1536", 40, 1536, 1536, 4},
};

// --cpu-time: process CPU time instead of the wall clock. With --threads 1 it measures the work of one core even
// while other jobs share the machine (they take wall time, not this process's CPU time).
bool g_cpu_time = false;

double seconds_now() {
  if (g_cpu_time) {
    timespec ts;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
  }
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

// Best-of-5 mean time per call, each batch at least min_batch_s long: the minimum filters out the
// other processes sharing this machine's two cores.
double time_call(const std::function<void()>& fn, double min_batch_s) {
  fn();
  int reps = 1;
  for (;;) {
    const double t0 = seconds_now();
    for (int i = 0; i < reps; ++i) fn();
    const double dt = seconds_now() - t0;
    if (dt >= min_batch_s) break;
    reps = std::max(reps * 2, int(reps * min_batch_s / std::max(dt, 1e-6)));
  }
  double best = 1e30;
  for (int batch = 0; batch < 5; ++batch) {
    const double t0 = seconds_now();
    for (int i = 0; i < reps; ++i) fn();
    best = std::min(best, (seconds_now() - t0) / reps);
  }
  return best;
}

float max_rel_diff(const std::vector<float>& a, const std::vector<float>& ref) {
  float scale = 0, diff = 0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    scale = std::max(scale, std::abs(ref[i]));
    diff = std::max(diff, std::abs(a[i] - ref[i]));
  }
  return diff / std::max(scale, 1e-30f);
}

using dt = dnnl::memory::data_type;
using tag = dnnl::memory::format_tag;
namespace detail = tether::cpu::detail;

struct Variant {
  const char* name;
  const char* what;
};
const Variant kVariants[] = {
    {"OpenBLAS", "cblas_sgemm, W [N,K] in place"},
    {"mm-f32", "oneDNN matmul, f32, W packed once (Tether's fp32 path)"},
    {"mm-bf16", "oneDNN matmul, bf16 x and W packed once, f32 accumulation (native bf16; n/a without it)"},
    {"pnl-f32", "Tether panel GEMM, f32 weights"},
    {"pnl-bf16", "Tether panel GEMM, bf16 weights widened in the kernel, f32 x"},
    {"pnl-f16", "Tether panel GEMM, fp16 weights widened in the kernel, f32 x"},
    {"cvt+mm", "bf16 W [N,K] widened to an f32 copy, then oneDNN matmul on it in place"},
};
constexpr int kNumVariants = int(sizeof kVariants / sizeof kVariants[0]);

struct Row {
  const GemmShape* shape;
  double secs[kNumVariants] = {};  // 0: not available here
  double err[kNumVariants] = {};   // max |y - y_OpenBLAS| / max |y_OpenBLAS|
};

}  // namespace

int main(int argc, char** argv) try {
  int threads = 2;
  double min_batch_s = 0.05;
  std::string model = "smolvla";
  std::string only;  // run only the shapes whose "group name" contains this text
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--threads") && i + 1 < argc) threads = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--min-batch-ms") && i + 1 < argc) min_batch_s = std::atof(argv[++i]) / 1e3;
    else if (!std::strcmp(argv[i], "--cpu-time")) g_cpu_time = true;
    else if (!std::strcmp(argv[i], "--model") && i + 1 < argc) model = argv[++i];
    else if (!std::strcmp(argv[i], "--only") && i + 1 < argc) only = argv[++i];
    else {
      std::fprintf(stderr, "usage: gemm_shapes [--threads N] [--min-batch-ms MS] [--cpu-time] "
                           "[--model smolvla|pi0|pi05|gr00t_n17] [--only TEXT]\n");
      return 2;
    }
  }
  omp_set_num_threads(threads);
  const tether::cpu::CpuPaths& paths = tether::cpu::cpu_paths();  // applies TETHER_MAX_CPU_ISA before oneDNN starts
  const detail::PanelKernel& panel = detail::panel_kernel();
  dnnl::engine eng(dnnl::engine::kind::cpu, 0);
  dnnl::stream strm(eng);
  std::printf("OpenBLAS: %s\noneDNN: %d.%d.%d, ISA %s\nTether dispatch: %s; panel kernel %s\nthreads: %d (OpenMP, "
              "one runtime)\n\n",
              tether::cpu::blas_name(), dnnl_version()->major, dnnl_version()->minor, dnnl_version()->patch,
              paths.onednn_isa.c_str(), tether::cpu::cpu_paths_summary().c_str(), panel.name, threads);

  std::vector<Row> rows;
  std::mt19937 gen(1);
  std::uniform_real_distribution<float> dist(-1.0f, 1.0f);
  if (model != "smolvla" && model != "pi0" && model != "pi05" && model != "gr00t_n17") {
    std::fprintf(stderr, "gemm_shapes: --model must be smolvla, pi0, pi05 or gr00t_n17\n");
    return 2;
  }
  // pi0.5's GEMMs are pi0's (its adaptive norms' projections run once per step, not per token).
  std::vector<GemmShape> shapes(std::begin(kShapes), std::end(kShapes));
  if (model == "pi0" || model == "pi05") shapes.assign(std::begin(kPi0Shapes), std::end(kPi0Shapes));
  if (model == "gr00t_n17") shapes.assign(std::begin(kGr00tN17Shapes), std::end(kGr00tN17Shapes));
  std::erase_if(shapes, [&](const GemmShape& s) {
    return (std::string(s.group) + " " + s.name).find(only) == std::string::npos;
  });
  if (shapes.empty()) {
    std::fprintf(stderr, "gemm_shapes: no %s shape matches --only '%s'\n", model.c_str(), only.c_str());
    return 2;
  }
  for (const GemmShape& s : shapes) {
    const int64_t m = s.m, n = s.n, k = s.k;
    std::vector<float> x(std::size_t(m * k)), w(std::size_t(n * k)), ref(std::size_t(m * n)), y(ref.size());
    for (auto& v : x) v = dist(gen);
    for (auto& v : w) v = dist(gen) * 0.05f;
    Row row{&s};

    auto openblas = [&] {
      cblas_sgemm(CblasRowMajor, CblasNoTrans, CblasTrans, int(m), int(n), int(k), 1.0f, x.data(), int(k),
                  w.data(), int(k), 0.0f, y.data(), int(n));
    };
    openblas();
    ref = y;

    // oneDNN matmul: W [N,K] row-major is the {K,N} matrix in format `ba`.
    const dnnl::memory::desc src_md({m, k}, dt::f32, tag::ab), dst_md({m, n}, dt::f32, tag::ab);
    const dnnl::memory::desc w_user_md({k, n}, dt::f32, tag::ba);
    dnnl::memory src_mem(src_md, eng, x.data()), dst_mem(dst_md, eng, y.data());
    dnnl::memory w_user(w_user_md, eng, w.data());
    dnnl::matmul::primitive_desc packed_pd(dnnl::matmul::desc(src_md, dnnl::memory::desc({k, n}, dt::f32, tag::any),
                                                              dst_md), eng);
    dnnl::memory w_packed(packed_pd.weights_desc(), eng);
    dnnl::reorder(w_user, w_packed).execute(strm, w_user, w_packed);
    dnnl::matmul packed(packed_pd);
    auto mm_f32 = [&] {
      packed.execute(strm, {{DNNL_ARG_SRC, src_mem}, {DNNL_ARG_WEIGHTS, w_packed}, {DNNL_ARG_DST, dst_mem}});
      strm.wait();
    };

    // Native bf16 (x converted outside the timing); absent where oneDNN has no bf16 matmul.
    std::function<void()> mm_bf16;
    dnnl::memory src_bf, w_bf;
    dnnl::matmul bf;
    try {
      const dnnl::memory::desc src_bf_md({m, k}, dt::bf16, tag::ab);
      dnnl::matmul::primitive_desc bf_pd(
          dnnl::matmul::desc(src_bf_md, dnnl::memory::desc({k, n}, dt::bf16, tag::any), dst_md), eng);
      src_bf = dnnl::memory(src_bf_md, eng);
      w_bf = dnnl::memory(bf_pd.weights_desc(), eng);
      dnnl::reorder(src_mem, src_bf).execute(strm, src_mem, src_bf);
      dnnl::reorder(w_user, w_bf).execute(strm, w_user, w_bf);
      bf = dnnl::matmul(bf_pd);
      mm_bf16 = [&] {
        bf.execute(strm, {{DNNL_ARG_SRC, src_bf}, {DNNL_ARG_WEIGHTS, w_bf}, {DNNL_ARG_DST, dst_mem}});
        strm.wait();
      };
    } catch (const dnnl::error&) {
    }
    strm.wait();

    // The panel GEMM, one packing per weight type.
    const auto pf32 = detail::pack_f32_panels(w.data(), n, k, panel.panel_width);
    const auto pbf16 = detail::pack_half_panels(w.data(), n, k, panel.panel_width, detail::PanelType::bf16);
    const auto pf16 = detail::pack_half_panels(w.data(), n, k, panel.panel_width, detail::PanelType::f16);
    const auto pbias = detail::pad_bias(nullptr, n, panel.panel_width);
    auto panel_run = [&](detail::PanelType t, const void* data) {
      return [&, t, data] { panel.get(t)({x.data(), m, k, k, data, n, pbias.data(), y.data(), n, false}); };
    };

    // bf16 W kept as [N,K], widened into an f32 copy before each call, then oneDNN on the copy in place.
    std::vector<uint16_t> w_half(w.size());
    for (std::size_t i = 0; i < w.size(); ++i) w_half[i] = tether::f32_to_bf16(w[i]);
    std::vector<float> w_wide(w.size());
    dnnl::memory w_wide_mem(w_user_md, eng, w_wide.data());
    dnnl::matmul plain(dnnl::matmul::primitive_desc(dnnl::matmul::desc(src_md, w_user_md, dst_md), eng));
    auto convert_then_mm = [&] {
      const int64_t total = int64_t(w_half.size());
#pragma omp parallel for
      for (int64_t i = 0; i < total; ++i) w_wide[std::size_t(i)] = tether::bf16_to_f32(w_half[std::size_t(i)]);
      plain.execute(strm, {{DNNL_ARG_SRC, src_mem}, {DNNL_ARG_WEIGHTS, w_wide_mem}, {DNNL_ARG_DST, dst_mem}});
      strm.wait();
    };

    const std::function<void()> fns[kNumVariants] = {openblas,
                                                     mm_f32,
                                                     mm_bf16,
                                                     panel_run(detail::PanelType::f32, pf32.data()),
                                                     panel_run(detail::PanelType::bf16, pbf16.data()),
                                                     panel_run(detail::PanelType::f16, pf16.data()),
                                                     convert_then_mm};
    for (int v = 0; v < kNumVariants; ++v) {
      if (!fns[v]) continue;
      std::fill(y.begin(), y.end(), 0.0f);
      row.secs[v] = time_call(fns[v], min_batch_s);
      row.err[v] = max_rel_diff(y, ref);
    }
    rows.push_back(row);
  }

  std::printf("GFLOP/s at %d threads; n/a: not available on this CPU. relerr = max |y - y_OpenBLAS| / max |y_OpenBLAS|.\n",
              threads);
  for (const Variant& v : kVariants) std::printf("  %-9s %s\n", v.name, v.what);
  std::printf("\n%-10s %-27s %16s %5s", "group", "shape", "MxNxK", "calls");
  for (const Variant& v : kVariants) std::printf(" %8.8s", v.name);
  std::printf("   relerr: %-8s %-8s %-8s\n", "mm-bf16", "pnl-bf16", "pnl-f16");
  double total[kNumVariants] = {};
  double best_f32 = 0;
  for (const Row& r : rows) {
    const GemmShape& s = *r.shape;
    const double flops = 2.0 * double(s.m) * double(s.n) * double(s.k);
    char dims[40];
    std::snprintf(dims, sizeof dims, "%lldx%lldx%lld", (long long)s.m, (long long)s.n, (long long)s.k);
    std::printf("%-10s %-27s %16s %5d", s.group, s.name, dims, s.calls);
    for (int v = 0; v < kNumVariants; ++v) {
      if (r.secs[v] > 0) std::printf(" %8.1f", flops / r.secs[v] / 1e9);
      else std::printf(" %8s", "n/a");
      total[v] += s.calls * r.secs[v];
    }
    for (int v : {0, 1, 3}) best_f32 = std::max(best_f32, r.secs[v] > 0 ? flops / r.secs[v] / 1e9 : 0.0);
    std::printf("           %-8.1e %-8.1e %-8.1e\n", r.err[2], r.err[4], r.err[5]);
  }
  std::printf("\nGEMM time per inference (sum of calls x time, seconds):\n");
  for (int v = 0; v < kNumVariants; ++v) {
    if (rows.front().secs[v] > 0) std::printf("  %-9s %7.3f\n", kVariants[v].name, total[v]);
    else std::printf("  %-9s %7s\n", kVariants[v].name, "n/a");
  }
  std::printf("\nper group (seconds per inference):\n%-10s", "group");
  for (const Variant& v : kVariants) std::printf(" %8.8s", v.name);
  std::printf("\n");
  std::vector<std::string> groups;  // in table order
  for (const Row& r : rows)
    if (std::find(groups.begin(), groups.end(), r.shape->group) == groups.end()) groups.push_back(r.shape->group);
  for (const std::string& group : groups) {
    std::printf("%-10s", group.c_str());
    for (int v = 0; v < kNumVariants; ++v) {
      double t = 0;
      for (const Row& r : rows)
        if (group == r.shape->group) t += r.shape->calls * r.secs[v];
      if (rows.front().secs[v] > 0) std::printf(" %8.3f", t);
      else std::printf(" %8s", "n/a");
    }
    std::printf("\n");
  }
  std::printf("\nbest measured fp32 GEMM rate: %.1f GFLOP/s (%d threads, best shape of OpenBLAS / oneDNN / panel)\n",
              best_f32, threads);
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "error: %s\n", e.what());
  return 2;
}
