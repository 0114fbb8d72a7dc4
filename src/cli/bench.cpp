// `tether bench`: latency distribution, per-stage breakdown, throughput and peak RSS of a checkpoint.
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <iostream>
#include <numeric>

#include "backend/cpu/gemm.h"
#include "cli/commands.h"
#include "cli/observation_args.h"
#include "core/json_util.h"
#include "core/safetensors.h"
#include "policy/policy.h"

namespace tether::cli {

namespace {

struct BenchArgs {
  std::string checkpoint;
  ObservationArgs observation;
  std::string precision = "fp32";
  int iterations = 100, warmup = 5, batch = 1;
  bool json = false;
  std::string out;
};

double peak_rss_mb() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return double(u.ru_maxrss) / 1024.0;  // Linux reports KiB
}

double percentile(std::vector<double> v, double p) {
  std::sort(v.begin(), v.end());
  const double rank = p / 100.0 * double(v.size() - 1);
  const std::size_t lo = std::size_t(rank);
  const std::size_t hi = std::min(lo + 1, v.size() - 1);
  return v[lo] + (v[hi] - v[lo]) * (rank - double(lo));
}

int run_bench(const BenchArgs& a) {
  if (a.iterations < 1 || a.warmup < 0 || a.batch < 1)
    throw Error(ErrorCode::invalid_argument, "--iterations and --batch must be >= 1, --warmup >= 0");
  const auto t0 = std::chrono::steady_clock::now();
  auto policy = policy::Policy::load(a.checkpoint, load_options(a.precision));
  const double load_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  const policy::Observation obs = a.observation.build(*policy);
  const std::vector<policy::Observation> batch(std::size_t(a.batch), obs);

  for (int i = 0; i < a.warmup; ++i) policy->predict(batch);
  std::vector<double> total, vision, prefix, denoise, pre, post;
  policy::Prediction last;
  const auto start = std::chrono::steady_clock::now();
  for (int i = 0; i < a.iterations; ++i) {
    last = policy->predict(batch);
    total.push_back(last.total_ms);
    pre.push_back(last.normalize_ms + last.timings.preprocess_ms);
    vision.push_back(last.timings.vision_ms);
    prefix.push_back(last.timings.prefix_ms);
    denoise.push_back(last.timings.denoise_ms);
    post.push_back(last.postprocess_ms);
  }
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  auto mean = [](const std::vector<double>& v) { return std::accumulate(v.begin(), v.end(), 0.0) / double(v.size()); };

  if (!a.out.empty()) {
    const auto& spec = policy->spec();
    std::vector<float> all;
    for (const auto& item : last.items) all.insert(all.end(), item.actions.begin(), item.actions.end());
    write_safetensors(a.out, {{"actions", Tensor::from_f32({int64_t(a.batch), spec.chunk_size, spec.action_dim}, all)}});
  }
  const Json report = {
      {"checkpoint", a.checkpoint},
      {"family", policy->spec().family},
      {"inference_mode", inference_mode(policy->spec())},
      {"batch", a.batch},
      {"iterations", a.iterations},
      {"warmup", a.warmup},
      {"load_ms", load_ms},
      {"latency_ms",
       {{"mean", mean(total)},
        {"p50", percentile(total, 50)},
        {"p95", percentile(total, 95)},
        {"p99", percentile(total, 99)},
        {"max", *std::max_element(total.begin(), total.end())}}},
      {"stages_ms",
       {{"preprocess", mean(pre)}, {"vision", mean(vision)}, {"prefix", mean(prefix)}, {"denoise", mean(denoise)},
        {"post", mean(post)}}},
      {"throughput_per_s", double(a.iterations) * a.batch / wall_s},
      {"peak_rss_mb", peak_rss_mb()},
      {"blas", cpu::blas_name()},
      {"threads", cpu::blas_threads()},
  };
  if (a.json) {
    std::cout << report.dump(2) << "\n";
    return kExitOk;
  }
  std::printf("%s  (%s, %s, batch %d, %d iterations after %d warm-up, %s x%d threads)\n", a.checkpoint.c_str(),
              policy->spec().family.c_str(), inference_mode(policy->spec()).c_str(), a.batch, a.iterations, a.warmup,
              cpu::blas_name(), cpu::blas_threads());
  std::printf("  latency ms   mean %.2f  p50 %.2f  p95 %.2f  p99 %.2f  max %.2f\n", report["latency_ms"]["mean"].get<double>(),
              report["latency_ms"]["p50"].get<double>(), report["latency_ms"]["p95"].get<double>(),
              report["latency_ms"]["p99"].get<double>(), report["latency_ms"]["max"].get<double>());
  std::printf("  stages ms    preprocess %.2f  vision %.2f  prefix %.2f  denoise %.2f  post %.2f\n", mean(pre),
              mean(vision), mean(prefix), mean(denoise), mean(post));
  std::printf("  throughput   %.2f chunks/s\n  peak RSS     %.1f MB\n  load         %.1f ms\n",
              report["throughput_per_s"].get<double>(), peak_rss_mb(), load_ms);
  return kExitOk;
}

}  // namespace

Verb add_bench(CLI::App& app) {
  auto args = std::make_shared<BenchArgs>();
  CLI::App* sub = app.add_subcommand("bench", "Measure latency, stage breakdown, throughput and peak RSS");
  sub->add_option("checkpoint", args->checkpoint, "Checkpoint directory")->required();
  sub->add_option("--iterations", args->iterations, "Timed runs")->capture_default_str();
  sub->add_option("--warmup", args->warmup, "Untimed runs first")->capture_default_str();
  sub->add_option("--batch", args->batch, "Observations per forward pass")->capture_default_str();
  sub->add_flag("--json", args->json, "Print JSON");
  sub->add_option("--out", args->out, "Write the last action chunk(s) to this safetensors file ('actions')");
  args->observation.add_to(sub, /*required=*/false);
  add_precision_flag(sub, args->precision);
  return {sub, [args] { return run_bench(*args); }};
}

}  // namespace tether::cli
