// Times SmolVLA's full-size GEMM shapes (y[M,N] = x[M,K] W[N,K]^T) on OpenBLAS and oneDNN, f32 and bf16,
// to choose the library behind tether::cpu::gemm. Results and the decision: bench/GEMM.md.
#include <cblas.h>
#include <omp.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <oneapi/dnnl/dnnl.hpp>
#include <random>
#include <string>
#include <vector>

#include "backend/cpu/gemm.h"

namespace {

struct GemmShape {
  const char* group;
  const char* name;
  int64_t m, n, k;
  // Calls per inference of a 3-camera SmolVLA (12 SigLIP layers per image, 16 VLM layers, 16 expert
  // layers of which 8 cross-attend, 10 denoising steps); 0 marks an alternative length, not counted.
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

double seconds_now() {
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

struct Row {
  const GemmShape* shape;
  std::vector<double> secs;  // per variant
  double max_rel_diff_f32 = 0, max_rel_diff_bf16 = 0;
};

float max_rel_diff(const std::vector<float>& a, const std::vector<float>& ref) {
  float scale = 0, diff = 0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    scale = std::max(scale, std::abs(ref[i]));
    diff = std::max(diff, std::abs(a[i] - ref[i]));
  }
  return diff / std::max(scale, 1e-30f);
}

const char* isa_name(dnnl::cpu_isa isa) {
  switch (isa) {
    case dnnl::cpu_isa::avx2: return "avx2";
    case dnnl::cpu_isa::avx2_vnni: return "avx2_vnni";
    case dnnl::cpu_isa::avx512_core: return "avx512_core";
    case dnnl::cpu_isa::avx512_core_vnni: return "avx512_core_vnni";
    case dnnl::cpu_isa::avx512_core_bf16: return "avx512_core_bf16";
    case dnnl::cpu_isa::avx512_core_amx: return "avx512_core_amx";
    default: return "other";
  }
}

}  // namespace

int main(int argc, char** argv) {
  int threads = 2;
  double min_batch_s = 0.05;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--threads") && i + 1 < argc) threads = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--min-batch-ms") && i + 1 < argc) min_batch_s = std::atof(argv[++i]) / 1e3;
    else {
      std::fprintf(stderr, "usage: gemm_shapes [--threads N] [--min-batch-ms MS]\n");
      return 2;
    }
  }
  using dt = dnnl::memory::data_type;
  using tag = dnnl::memory::format_tag;
  dnnl::engine eng(dnnl::engine::kind::cpu, 0);
  dnnl::stream strm(eng);
  std::printf("OpenBLAS: %s\noneDNN: %d.%d.%d, ISA %s\nthreads: %d (OpenMP, one runtime)\n\n", tether::cpu::blas_name(),
              dnnl_version()->major, dnnl_version()->minor, dnnl_version()->patch,
              isa_name(dnnl::get_effective_cpu_isa()), threads);

  // Five libraries/set-ups, each timed at `threads` and then at 1 thread.
  const char* variants[] = {"OpenBLAS", "dnnlsgem", "mm-plnW", "mm-pckW", "mm-bf16",
                            "OB/1t",    "dsgem/1t", "plnW/1t", "pckW/1t", "bf16/1t"};
  const int nvar = 10;
  std::vector<Row> rows;
  std::mt19937 gen(1);
  std::uniform_real_distribution<float> dist(-1.0f, 1.0f);
  for (const GemmShape& s : kShapes) {
    const int64_t m = s.m, n = s.n, k = s.k;
    std::vector<float> x(std::size_t(m * k)), w(std::size_t(n * k)), ref(std::size_t(m * n)), y(ref.size());
    for (auto& v : x) v = dist(gen);
    for (auto& v : w) v = dist(gen) * 0.05f;
    Row row{&s, std::vector<double>(nvar, 0.0)};

    auto openblas = [&] {
      cblas_sgemm(CblasRowMajor, CblasNoTrans, CblasTrans, int(m), int(n), int(k), 1.0f, x.data(), int(k),
                  w.data(), int(k), 0.0f, ref.data(), int(n));
    };
    auto onednn_sgemm = [&] { dnnl_sgemm('N', 'T', m, n, k, 1.0f, x.data(), k, w.data(), k, 0.0f, y.data(), n); };

    // Matmul primitives: W [N,K] row-major is the {K,N} matrix in format `ba`.
    dnnl::memory::desc src_md({m, k}, dt::f32, tag::ab), dst_md({m, n}, dt::f32, tag::ab);
    dnnl::memory::desc w_user_md({k, n}, dt::f32, tag::ba);
    dnnl::memory src_mem(src_md, eng, x.data()), dst_mem(dst_md, eng, y.data());
    dnnl::memory w_user(w_user_md, eng, w.data());

    dnnl::matmul::primitive_desc plain_pd(dnnl::matmul::desc(src_md, w_user_md, dst_md), eng);
    dnnl::matmul plain(plain_pd);
    auto run_plain = [&] {
      plain.execute(strm, {{DNNL_ARG_SRC, src_mem}, {DNNL_ARG_WEIGHTS, w_user}, {DNNL_ARG_DST, dst_mem}});
      strm.wait();
    };

    dnnl::memory::desc w_any({k, n}, dt::f32, tag::any);
    dnnl::matmul::primitive_desc packed_pd(dnnl::matmul::desc(src_md, w_any, dst_md), eng);
    dnnl::memory w_packed(packed_pd.weights_desc(), eng);
    dnnl::reorder(w_user, w_packed).execute(strm, w_user, w_packed);
    dnnl::matmul packed(packed_pd);
    auto run_packed = [&] {
      packed.execute(strm, {{DNNL_ARG_SRC, src_mem}, {DNNL_ARG_WEIGHTS, w_packed}, {DNNL_ARG_DST, dst_mem}});
      strm.wait();
    };

    // bf16 inputs (converted once, outside the timing), f32 output.
    dnnl::memory::desc src_bf_md({m, k}, dt::bf16, tag::ab), w_bf_any({k, n}, dt::bf16, tag::any);
    dnnl::matmul::primitive_desc bf_pd(dnnl::matmul::desc(src_bf_md, w_bf_any, dst_md), eng);
    dnnl::memory src_bf(src_bf_md, eng), w_bf(bf_pd.weights_desc(), eng);
    dnnl::reorder(src_mem, src_bf).execute(strm, src_mem, src_bf);
    dnnl::reorder(w_user, w_bf).execute(strm, w_user, w_bf);
    dnnl::matmul bf(bf_pd);
    std::vector<float> y_bf(ref.size());
    dnnl::memory dst_bf(dst_md, eng, y_bf.data());
    auto run_bf = [&] {
      bf.execute(strm, {{DNNL_ARG_SRC, src_bf}, {DNNL_ARG_WEIGHTS, w_bf}, {DNNL_ARG_DST, dst_bf}});
      strm.wait();
    };
    strm.wait();

    const std::function<void()> fns[] = {openblas, onednn_sgemm, run_plain, run_packed, run_bf};
    for (int pass = 0; pass < 2; ++pass) {
      omp_set_num_threads(pass == 0 ? threads : 1);
      for (int v = 0; v < 5; ++v) {
        std::fill(y.begin(), y.end(), 0.0f);
        row.secs[std::size_t(pass * 5 + v)] = time_call(fns[v], min_batch_s);
        if (v == 1 || v == 2 || v == 3) row.max_rel_diff_f32 = std::max<double>(row.max_rel_diff_f32, max_rel_diff(y, ref));
      }
    }
    row.max_rel_diff_bf16 = max_rel_diff(y_bf, ref);
    omp_set_num_threads(threads);
    rows.push_back(row);
  }

  std::printf(
      "GFLOP/s, %d threads unless marked /1t. OB = OpenBLAS; dnnlsgem = dnnl_sgemm; mm = oneDNN matmul;\n"
      "plnW = W used in place ([N,K] row-major, as mmap'ed); pckW = W reordered once to the primitive's\n"
      "preferred layout; bf16 = bf16 x and packed bf16 W (converted outside the timing), f32 accumulation\n"
      "and output. relerr = max |y - y_OpenBLAS| / max |y_OpenBLAS|.\n\n",
      threads);
  std::printf("%-10s %-27s %16s %5s", "group", "shape", "MxNxK", "calls");
  for (int v = 0; v < nvar; ++v) std::printf(" %8.8s", variants[v]);
  std::printf(" %9s %9s\n", "relerr32", "relerr16");
  std::vector<double> total(nvar, 0.0);
  for (const Row& r : rows) {
    const GemmShape& s = *r.shape;
    const double flops = 2.0 * double(s.m) * double(s.n) * double(s.k);
    char dims[40];
    std::snprintf(dims, sizeof dims, "%lldx%lldx%lld", (long long)s.m, (long long)s.n, (long long)s.k);
    std::printf("%-10s %-27s %16s %5d", s.group, s.name, dims, s.calls);
    for (int v = 0; v < nvar; ++v) {
      std::printf(" %8.1f", flops / r.secs[std::size_t(v)] / 1e9);
      total[std::size_t(v)] += s.calls * r.secs[std::size_t(v)];
    }
    std::printf(" %9.1e %9.1e\n", r.max_rel_diff_f32, r.max_rel_diff_bf16);
  }
  std::printf("\nGEMM time per inference (sum of calls x time, seconds):\n");
  for (int v = 0; v < nvar; ++v) std::printf("  %-18s %7.3f\n", variants[v], total[std::size_t(v)]);
  std::printf("\nper group (seconds per inference):\n%-10s", "group");
  for (int v = 0; v < nvar; ++v) std::printf(" %8.8s", variants[v]);
  std::printf("\n");
  for (const char* group : {"vision", "connector", "prefix241", "expert"}) {
    std::printf("%-10s", group);
    for (int v = 0; v < nvar; ++v) {
      double t = 0;
      for (const Row& r : rows)
        if (!std::strcmp(r.shape->group, group)) t += r.shape->calls * r.secs[std::size_t(v)];
      std::printf(" %8.3f", t);
    }
    std::printf("\n");
  }
  return 0;
}
