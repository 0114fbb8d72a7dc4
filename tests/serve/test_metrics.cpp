// Prometheus text output: histogram bucket semantics, label escaping, every series the contract names.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <unistd.h>

#include "core/error.h"
#include "serve/metrics.h"

using namespace tether::serve;

namespace {
bool has_line(const std::string& text, const std::string& line) {
  return ("\n" + text).find("\n" + line + "\n") != std::string::npos;
}
}  // namespace

TEST(Histogram, BucketsAreUpperInclusive) {
  Histogram h({0.1, 1, 10});
  for (double v : {0.05, 0.1, 0.5, 1.0, 20.0}) h.observe(v);
  EXPECT_EQ(h.counts(), std::vector<uint64_t>({2, 2, 0, 1}));
  EXPECT_EQ(h.count(), 5u);
  EXPECT_DOUBLE_EQ(h.sum(), 21.65);
}

TEST(Metrics, RendersTheContractSeries) {
  Metrics m("0.1.0", "oneDNN 2.6");
  m.declare_stages({"preprocess", "vision", "prefix", "denoise"});  // the model's, once it has loaded
  m.count_request("/act", 200);
  m.count_request("/act", 200);
  m.count_request("/act", 503);
  m.observe_stage("total", 0.004);
  m.observe_stage("total", 0.02);
  m.observe_batch_size(3);
  m.set_queue_depth(5);
  m.set_model_ready(true);
  const std::string t = m.render();
  EXPECT_TRUE(has_line(t, "# TYPE tether_requests_total counter")) << t;
  EXPECT_TRUE(has_line(t, "tether_requests_total{transport=\"http\",endpoint=\"/act\",status=\"200\"} 2")) << t;
  EXPECT_TRUE(has_line(t, "tether_requests_total{transport=\"http\",endpoint=\"/act\",status=\"503\"} 1")) << t;
  EXPECT_TRUE(has_line(t, "# TYPE tether_request_duration_seconds histogram")) << t;
  // Cumulative buckets: 0.004 lands in le=0.005, 0.02 in le=0.025.
  EXPECT_TRUE(has_line(t, "tether_request_duration_seconds_bucket{stage=\"total\",le=\"0.0025\"} 0")) << t;
  EXPECT_TRUE(has_line(t, "tether_request_duration_seconds_bucket{stage=\"total\",le=\"0.005\"} 1")) << t;
  EXPECT_TRUE(has_line(t, "tether_request_duration_seconds_bucket{stage=\"total\",le=\"0.025\"} 2")) << t;
  EXPECT_TRUE(has_line(t, "tether_request_duration_seconds_bucket{stage=\"total\",le=\"+Inf\"} 2")) << t;
  EXPECT_TRUE(has_line(t, "tether_request_duration_seconds_sum{stage=\"total\"} 0.024")) << t;
  EXPECT_TRUE(has_line(t, "tether_request_duration_seconds_count{stage=\"total\"} 2")) << t;
  for (const char* stage : {"queue", "preprocess", "vision", "prefix", "denoise", "postprocess"})
    EXPECT_TRUE(has_line(t, std::string("tether_request_duration_seconds_count{stage=\"") + stage + "\"} 0")) << stage;
  EXPECT_TRUE(has_line(t, "tether_queue_depth 5")) << t;
  EXPECT_TRUE(has_line(t, "tether_batch_size_bucket{le=\"2\"} 0")) << t;
  EXPECT_TRUE(has_line(t, "tether_batch_size_bucket{le=\"4\"} 1")) << t;
  EXPECT_TRUE(has_line(t, "tether_batch_size_count 1")) << t;
  EXPECT_TRUE(has_line(t, "tether_build_info{version=\"0.1.0\",gemm=\"oneDNN 2.6\"} 1")) << t;
  EXPECT_TRUE(has_line(t, "tether_model_ready 1")) << t;
  // Every sample line is "name{labels} value" or "name value"; every metric has HELP and TYPE.
  std::stringstream ss(t);
  for (std::string line; std::getline(ss, line);) {
    if (line.rfind("# ", 0) == 0) continue;
    EXPECT_EQ(line.rfind("tether_", 0), 0u) << line;
    EXPECT_NE(line.find(' '), std::string::npos) << line;
  }
}

TEST(Metrics, EscapesLabelValues) {
  EXPECT_EQ(escape_label("a\"b\\c\nd"), "a\\\"b\\\\c\\nd");
  Metrics m("1", "x\"y");
  EXPECT_NE(m.render().find("gemm=\"x\\\"y\""), std::string::npos);
}
