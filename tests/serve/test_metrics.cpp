// Prometheus text output: histogram bucket semantics, label escaping, every series the contract names; SHA-256
// against the FIPS test vectors (it names the served weights).
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <unistd.h>

#include "core/error.h"
#include "serve/metrics.h"
#include "serve/sha256.h"

using namespace tether::serve;

namespace {
bool has_line(const std::string& text, const std::string& line) {
  return ("\n" + text).find("\n" + line + "\n") != std::string::npos;
}
std::string sha_hex(const std::string& s) {
  Sha256 h;
  h.update(reinterpret_cast<const uint8_t*>(s.data()), s.size());
  const auto d = h.finish();
  return to_hex(d.data(), d.size());
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
  EXPECT_TRUE(has_line(t, "tether_requests_total{endpoint=\"/act\",status=\"200\"} 2")) << t;
  EXPECT_TRUE(has_line(t, "tether_requests_total{endpoint=\"/act\",status=\"503\"} 1")) << t;
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

TEST(Sha256, FipsVectors) {
  EXPECT_EQ(sha_hex(""), "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
  EXPECT_EQ(sha_hex("abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
  EXPECT_EQ(sha_hex("abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq"),
            "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1");
  // One million 'a', fed in uneven pieces to exercise the block buffering.
  Sha256 h;
  const std::string chunk(997, 'a');
  std::size_t left = 1000000;
  while (left > 0) {
    const std::size_t n = std::min(left, chunk.size());
    h.update(reinterpret_cast<const uint8_t*>(chunk.data()), n);
    left -= n;
  }
  const auto d = h.finish();
  EXPECT_EQ(to_hex(d.data(), d.size()), "cdc76e5c9914fb9281a1c7e284d73e67f1809a48a497200e046d39ccc7112cd0");
}

TEST(Sha256, HashesFiles) {
  const auto path = std::filesystem::temp_directory_path() / ("tether_sha_" + std::to_string(::getpid()));
  std::ofstream(path) << "abc";
  EXPECT_EQ(sha256_file_hex(path.string()), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
  std::filesystem::remove(path);
  EXPECT_THROW(sha256_file_hex(path.string()), tether::Error);
}
