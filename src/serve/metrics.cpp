// Prometheus text rendering; bucket bounds chosen for a policy server (1 ms .. 10 s, batches 1 .. 64).
#include "serve/metrics.h"

#include <algorithm>
#include <cstdio>
#include <cstdlib>

namespace tether::serve {

namespace {

const std::vector<double> kLatencyBounds = {0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1,
                                            0.25,  0.5,    1.0,   2.5,  5.0,   10.0};
const std::vector<double> kBatchBounds = {1, 2, 4, 8, 16, 32, 64};

// Shortest text that reads back to the same double; Prometheus accepts any Go ParseFloat syntax.
std::string num(double v) {
  if (v == double(int64_t(v)) && std::abs(v) < 1e15) return std::to_string(int64_t(v));  // counts stay integers
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.17g", v);
  for (int precision = 1; precision < 17; ++precision) {
    char shorter[32];
    std::snprintf(shorter, sizeof shorter, "%.*g", precision, v);
    if (std::strtod(shorter, nullptr) == v) return shorter;
  }
  return buf;
}

void render_histogram(std::string& out, const std::string& name, const std::string& labels, const Histogram& h) {
  const std::string sep = labels.empty() ? "" : ",";
  uint64_t cumulative = 0;
  for (std::size_t i = 0; i < h.bounds().size(); ++i) {
    cumulative += h.counts()[i];
    out += name + "_bucket{" + labels + sep + "le=\"" + num(h.bounds()[i]) + "\"} " + std::to_string(cumulative) + "\n";
  }
  cumulative += h.counts().back();
  out += name + "_bucket{" + labels + sep + "le=\"+Inf\"} " + std::to_string(cumulative) + "\n";
  const std::string braces = labels.empty() ? "" : "{" + labels + "}";
  out += name + "_sum" + braces + " " + num(h.sum()) + "\n";
  out += name + "_count" + braces + " " + std::to_string(h.count()) + "\n";
}

}  // namespace

Histogram::Histogram(std::vector<double> upper_bounds) : bounds_(std::move(upper_bounds)) {
  std::sort(bounds_.begin(), bounds_.end());
  counts_.assign(bounds_.size() + 1, 0);
}

void Histogram::observe(double value) {
  const auto it = std::lower_bound(bounds_.begin(), bounds_.end(), value);  // first bound >= value
  ++counts_[std::size_t(it - bounds_.begin())];
  sum_ += value;
  ++count_;
}

std::string escape_label(const std::string& value) {
  std::string out;
  for (char c : value) {
    if (c == '\\') out += "\\\\";
    else if (c == '"') out += "\\\"";
    else if (c == '\n') out += "\\n";
    else out += c;
  }
  return out;
}

Metrics::Metrics(std::string version, std::string gemm)
    : version_(std::move(version)), gemm_(std::move(gemm)), batch_sizes_(kBatchBounds) {
  // Every stage is present from the start, so dashboards see zeros rather than missing series; the model's own
  // stages join once it has loaded (declare_stages).
  for (const char* s : {"total", "queue", "postprocess"}) stages_.emplace(s, Histogram(kLatencyBounds));
}

void Metrics::declare_stages(const std::vector<std::string>& stages) {
  std::lock_guard lock(mu_);
  for (const auto& s : stages) stages_.emplace(s, Histogram(kLatencyBounds));
}

void Metrics::count_request(const std::string& endpoint, int status, const std::string& transport) {
  std::lock_guard lock(mu_);
  ++requests_[{transport, endpoint, status}];
}

void Metrics::observe_stage(const std::string& stage, double seconds) {
  std::lock_guard lock(mu_);
  auto it = stages_.find(stage);
  if (it == stages_.end()) it = stages_.emplace(stage, Histogram(kLatencyBounds)).first;
  it->second.observe(seconds);
}

void Metrics::observe_batch_size(int size) {
  std::lock_guard lock(mu_);
  batch_sizes_.observe(double(size));
}

void Metrics::set_queue_depth(int depth) {
  std::lock_guard lock(mu_);
  queue_depth_ = depth;
}

void Metrics::set_model_ready(bool ready) {
  std::lock_guard lock(mu_);
  model_ready_ = ready;
}

void Metrics::set_gemm(const std::string& gemm) {
  std::lock_guard lock(mu_);
  gemm_ = gemm;
}

void Metrics::add_counter(const std::string& name, const std::string& help, double value, const std::string& labels) {
  std::lock_guard lock(mu_);
  Family& f = families_[name];
  f.help = help;
  f.type = "counter";
  f.values[labels] += value;
}

void Metrics::set_gauge(const std::string& name, const std::string& help, double value, const std::string& labels) {
  std::lock_guard lock(mu_);
  Family& f = families_[name];
  f.help = help;
  f.type = "gauge";
  f.values[labels] = value;
}

std::string Metrics::render() const {
  std::lock_guard lock(mu_);
  std::string out;
  out += "# HELP tether_requests_total Requests answered, by transport, endpoint and status code.\n";
  out += "# TYPE tether_requests_total counter\n";
  for (const auto& [key, n] : requests_) {
    const auto& [transport, endpoint, status] = key;
    out += "tether_requests_total{transport=\"" + escape_label(transport) + "\",endpoint=\"" + escape_label(endpoint) +
           "\",status=\"" + std::to_string(status) + "\"} " + std::to_string(n) + "\n";
  }
  out += "# HELP tether_request_duration_seconds Latency of /act requests by stage (total = received to answered).\n";
  out += "# TYPE tether_request_duration_seconds histogram\n";
  for (const auto& [stage, h] : stages_)
    render_histogram(out, "tether_request_duration_seconds", "stage=\"" + escape_label(stage) + "\"", h);
  out += "# HELP tether_queue_depth Requests waiting for a forward pass.\n";
  out += "# TYPE tether_queue_depth gauge\n";
  out += "tether_queue_depth " + std::to_string(queue_depth_) + "\n";
  out += "# HELP tether_batch_size Requests sharing one forward pass.\n";
  out += "# TYPE tether_batch_size histogram\n";
  render_histogram(out, "tether_batch_size", "", batch_sizes_);
  out += "# HELP tether_build_info Build of this server.\n";
  out += "# TYPE tether_build_info gauge\n";
  out += "tether_build_info{version=\"" + escape_label(version_) + "\",gemm=\"" + escape_label(gemm_) + "\"} 1\n";
  out += "# HELP tether_model_ready 1 once the model is loaded and warmed up.\n";
  out += "# TYPE tether_model_ready gauge\n";
  out += std::string("tether_model_ready ") + (model_ready_ ? "1" : "0") + "\n";
  for (const auto& [name, f] : families_) {
    out += "# HELP " + name + " " + f.help + "\n# TYPE " + name + " " + f.type + "\n";
    for (const auto& [labels, v] : f.values) {
      char num[32];
      std::snprintf(num, sizeof num, "%.17g", v);
      out += name + (labels.empty() ? "" : "{" + labels + "}") + " " + num + "\n";
    }
  }
  return out;
}

}  // namespace tether::serve
