// Server metrics in the Prometheus text exposition format 0.0.4: request counts, per-stage latency histograms,
// batch sizes, queue depth, readiness. Thread-safe; rendering takes a consistent snapshot.
#pragma once

#include <cstdint>
#include <map>
#include <mutex>
#include <string>
#include <tuple>
#include <vector>

namespace tether::serve {

// Cumulative-bucket histogram (Prometheus semantics: bucket `le` counts observations <= le).
class Histogram {
 public:
  explicit Histogram(std::vector<double> upper_bounds);
  void observe(double value);
  const std::vector<double>& bounds() const { return bounds_; }
  // Per-bucket counts (not cumulative), one more than bounds (the last is +Inf).
  const std::vector<uint64_t>& counts() const { return counts_; }
  double sum() const { return sum_; }
  uint64_t count() const { return count_; }

 private:
  std::vector<double> bounds_;
  std::vector<uint64_t> counts_;
  double sum_ = 0;
  uint64_t count_ = 0;
};

class Metrics {
 public:
  Metrics(std::string version, std::string gemm);

  // `transport`: the way in (http, openpi, gr00t, zmq, kserve), a label of its own so that one dashboard shows every
  // robot's client.
  void count_request(const std::string& endpoint, int status, const std::string& transport = "http");
  // `stage`: total, queue, postprocess, or one of the model's stages (ModelSpec::stages).
  void observe_stage(const std::string& stage, double seconds);
  // The model's stages, so that their series exist (at zero) before the first request.
  void declare_stages(const std::vector<std::string>& stages);
  void observe_batch_size(int size);
  void set_queue_depth(int depth);
  void set_model_ready(bool ready);
  // The GEMM library is known once the model has loaded.
  void set_gemm(const std::string& gemm);
  // Counters and gauges of the safety wedges and the recorder: `name` is the full metric name, `labels` the label
  // list without braces (`joint="j1",limit="velocity"`), values kept per label set.
  void add_counter(const std::string& name, const std::string& help, double value = 1, const std::string& labels = "");
  void set_gauge(const std::string& name, const std::string& help, double value, const std::string& labels = "");

  std::string render() const;

 private:
  mutable std::mutex mu_;
  std::string version_, gemm_;
  std::map<std::tuple<std::string, std::string, int>, uint64_t> requests_;  // transport, endpoint, status
  std::map<std::string, Histogram> stages_;
  Histogram batch_sizes_;
  struct Family {
    std::string help, type;
    std::map<std::string, double> values;  // by label list
  };
  std::map<std::string, Family> families_;
  int queue_depth_ = 0;
  bool model_ready_ = false;
};

// Escapes a label value for the text format (backslash, double quote, newline).
std::string escape_label(const std::string& value);

}  // namespace tether::serve
