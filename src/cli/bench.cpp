// `tether bench`: latency distribution, per-stage breakdown, throughput and peak RSS of a checkpoint.
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <numeric>

#include "backend/cpu/cpu_features.h"
#include "backend/cpu/gemm.h"
#include "backend/cpu/packed_linear.h"
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
  std::string backend = "cpu";
  std::string embodiment_tag;
  int iterations = 100, warmup = 5, batch = 1;
  bool json = false;
  std::string out;
  double adaptive_threshold = -1;  // < 0: no adaptive comparison
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

double mean_of(const std::vector<double>& v) { return std::accumulate(v.begin(), v.end(), 0.0) / double(v.size()); }

// Every step against adaptive steps on the same seeded observations (seed, seed + 1, ... per item and iteration),
// interleaved so that load on the machine hits both alike: steps used, latency of each, and how far the adaptive
// actions land from the full-step ones.
Json compare_adaptive(policy::Policy& policy, const policy::Observation& obs, const BenchArgs& a) {
  // The sampler's stage: the model's last one.
  const std::string sampling = policy.spec().stages.empty() ? std::string() : policy.spec().stages.back();
  std::vector<double> full_ms, adaptive_ms, full_denoise, adaptive_denoise, steps;
  double max_diff = 0, max_action = 0;
  for (int i = 0; i < a.warmup + a.iterations; ++i) {
    std::vector<policy::Observation> batch(std::size_t(a.batch), obs);
    for (int j = 0; j < a.batch; ++j) batch[j].seed = obs.seed + uint64_t(i) * uint64_t(a.batch) + uint64_t(j);
    const policy::Prediction full = policy.predict(batch);
    for (auto& o : batch) o.adaptive_threshold = float(a.adaptive_threshold);
    const policy::Prediction fast = policy.predict(batch);
    if (i < a.warmup) continue;
    full_ms.push_back(full.total_ms);
    adaptive_ms.push_back(fast.total_ms);
    full_denoise.push_back(full.timings.get(sampling));
    adaptive_denoise.push_back(fast.timings.get(sampling));
    for (std::size_t j = 0; j < fast.items.size(); ++j) {
      steps.push_back(fast.items[j].denoise_steps_used);
      const auto& x = full.items[j].actions;
      const auto& y = fast.items[j].actions;
      for (std::size_t k = 0; k < x.size(); ++k) {
        max_diff = std::max(max_diff, double(std::fabs(x[k] - y[k])));
        max_action = std::max(max_action, double(std::fabs(x[k])));
      }
    }
  }
  return {{"threshold", a.adaptive_threshold},
          {"num_steps", policy.spec().num_steps},
          {"steps_used",
           {{"mean", mean_of(steps)},
            {"min", *std::min_element(steps.begin(), steps.end())},
            {"max", *std::max_element(steps.begin(), steps.end())}}},
          {"latency_ms", {{"full", mean_of(full_ms)}, {"adaptive", mean_of(adaptive_ms)}}},
          {"denoise_ms", {{"full", mean_of(full_denoise)}, {"adaptive", mean_of(adaptive_denoise)}}},
          {"max_abs_diff", max_diff},
          {"max_abs_action", max_action}};
}

int run_bench(const BenchArgs& a) {
  if (a.iterations < 1 || a.warmup < 0 || a.batch < 1)
    throw Error(ErrorCode::invalid_argument, "--iterations and --batch must be >= 1, --warmup >= 0");
  if (!std::isfinite(a.adaptive_threshold))
    throw Error(ErrorCode::invalid_argument, "--adaptive-threshold must be a finite number >= 0");
  const auto t0 = std::chrono::steady_clock::now();
  auto policy = policy::Policy::load(a.checkpoint, load_options(a.precision, a.embodiment_tag, a.backend));
  const double load_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  const policy::Observation obs = a.observation.build(*policy);
  const std::vector<policy::Observation> batch(std::size_t(a.batch), obs);

  for (int i = 0; i < a.warmup; ++i) policy->predict(batch);
  // Per model stage (the first one also carries the policy's normalisation), then the post-processing.
  const std::vector<std::string>& stage_names = policy->spec().stages;
  std::vector<std::vector<double>> stage_ms(stage_names.size());
  std::vector<double> total, post;
  policy::Prediction last;
  const auto start = std::chrono::steady_clock::now();
  for (int i = 0; i < a.iterations; ++i) {
    last = policy->predict(batch);
    total.push_back(last.total_ms);
    for (std::size_t s = 0; s < stage_names.size(); ++s)
      stage_ms[s].push_back(last.timings.get(stage_names[s]) + (s == 0 ? last.normalize_ms : 0.0));
    post.push_back(last.postprocess_ms);
  }
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const auto& mean = mean_of;

  if (!a.out.empty()) {
    const auto& spec = policy->spec();
    std::vector<float> all;
    for (const auto& item : last.items) all.insert(all.end(), item.actions.begin(), item.actions.end());
    write_safetensors(a.out, {{"actions", Tensor::from_f32({int64_t(a.batch), spec.chunk_size, spec.action_dim}, all)}});
  }
  Json report = {
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
      {"stages_ms", Json::object()},
      {"throughput_per_s", double(a.iterations) * a.batch / wall_s},
      // Matrix-product work (2 flops per multiply-add) per chunk, and the rate the mean latency achieves.
      {"gflop_per_chunk", last.flops / double(a.batch) / 1e9},
      {"gflop_per_s", last.flops / (mean(total) / 1e3) / 1e9},
      {"peak_rss_mb", peak_rss_mb()},
      {"blas", cpu::blas_name()},
      {"gemm", cpu::gemm_name(policy->spec().precision)},
      {"compute", cpu::compute_mode_description(policy->spec().precision)},
      {"cpu_dispatch", cpu::cpu_paths_summary()},
      {"threads", cpu::blas_threads()},
  };
  for (std::size_t s = 0; s < stage_names.size(); ++s) report["stages_ms"][stage_names[s]] = mean(stage_ms[s]);
  report["stages_ms"]["post"] = mean(post);
  if (a.adaptive_threshold >= 0) report["adaptive"] = compare_adaptive(*policy, obs, a);
  if (a.json) {
    std::cout << report.dump(2) << "\n";
    return kExitOk;
  }
  std::printf("%s  (%s, %s, batch %d, %d iterations after %d warm-up, %d threads)\n", a.checkpoint.c_str(),
              policy->spec().family.c_str(), inference_mode(policy->spec()).c_str(), a.batch, a.iterations, a.warmup,
              cpu::blas_threads());
  std::printf("  linear       %s\n  cpu          %s\n", report["compute"].get<std::string>().c_str(),
              report["cpu_dispatch"].get<std::string>().c_str());
  std::printf("  latency ms   mean %.2f  p50 %.2f  p95 %.2f  p99 %.2f  max %.2f\n", report["latency_ms"]["mean"].get<double>(),
              report["latency_ms"]["p50"].get<double>(), report["latency_ms"]["p95"].get<double>(),
              report["latency_ms"]["p99"].get<double>(), report["latency_ms"]["max"].get<double>());
  std::string stages_line;
  char cell[96];
  for (auto it = report["stages_ms"].begin(); it != report["stages_ms"].end(); ++it) {
    std::snprintf(cell, sizeof cell, "%s%s %.2f", stages_line.empty() ? "" : "  ", it.key().c_str(), it->get<double>());
    stages_line += cell;
  }
  std::printf("  stages ms    %s\n", stages_line.c_str());
  std::printf("  compute      %.2f GFLOP per chunk, %.1f GFLOP/s achieved\n", report["gflop_per_chunk"].get<double>(),
              report["gflop_per_s"].get<double>());
  std::printf("  throughput   %.2f chunks/s\n  peak RSS     %.1f MB\n  load         %.1f ms\n",
              report["throughput_per_s"].get<double>(), peak_rss_mb(), load_ms);
  if (report.contains("adaptive")) {
    const Json& r = report["adaptive"];
    std::printf("  adaptive     threshold %g: steps used mean %.2f min %d max %d (of %lld)\n", a.adaptive_threshold,
                r["steps_used"]["mean"].get<double>(), int(r["steps_used"]["min"].get<double>()),
                int(r["steps_used"]["max"].get<double>()), static_cast<long long>(policy->spec().num_steps));
    std::printf("               latency ms all steps %.2f, adaptive %.2f (denoise %.2f -> %.2f)\n",
                r["latency_ms"]["full"].get<double>(), r["latency_ms"]["adaptive"].get<double>(),
                r["denoise_ms"]["full"].get<double>(), r["denoise_ms"]["adaptive"].get<double>());
    std::printf("               max |diff| vs all steps %.4g (robot units; max |action| %.4g)\n",
                r["max_abs_diff"].get<double>(), r["max_abs_action"].get<double>());
  }
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
  sub->add_option("--adaptive-threshold", args->adaptive_threshold,
                  "Also run the same seeded observations (--seed, --seed + 1, ...) with every denoise step and with "
                  "adaptive steps at this threshold; report steps used, both latencies and the max |diff|")
      ->check(CLI::NonNegativeNumber);
  args->observation.add_to(sub, /*required=*/false);
  add_precision_flag(sub, args->precision);
  add_backend_flag(sub, args->backend);
  add_embodiment_tag_flag(sub, args->embodiment_tag);
  return {sub, [args] { return run_bench(*args); }};
}

}  // namespace tether::cli
