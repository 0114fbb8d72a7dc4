// Load generator for `tether serve`: N concurrent keep-alive clients each send POST /act in a loop; prints
// throughput, latency percentiles and the mean batch size the server reported, per concurrency level.
// Usage: serve_load --port P [--clients 1,4,16] [--requests 40] [--image FILE] [--state 0,90,90,45,0,20]
#include <algorithm>
#include <atomic>
#include <boost/asio.hpp>
#include <boost/beast.hpp>
#include <chrono>
#include <cstdio>
#include <exception>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "core/json_util.h"
#include "serve/base64.h"

namespace net = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
using Clock = std::chrono::steady_clock;
using tether::Json;

namespace {

struct Options {
  uint16_t port = 8000;
  std::vector<int> clients = {1, 4, 16};
  int requests = 40;  // per client
  std::string image, state = "0,90,90,45,0,20", instruction = "pick up the cube", key;
};

struct ClientStats {
  std::vector<double> latencies_ms;
  double batch_sum = 0;
  int errors = 0;
};

std::vector<std::string> split(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  for (std::string item; std::getline(ss, item, ',');) out.push_back(item);
  return out;
}

// The model's camera keys from GET /config, so the same image can be sent to every camera.
std::vector<std::string> fetch_cameras(const Options& o) {
  net::io_context ioc;
  beast::tcp_stream stream(ioc);
  stream.connect(net::ip::tcp::endpoint(net::ip::make_address("127.0.0.1"), o.port));
  http::request<http::empty_body> req{http::verb::get, "/config", 11};
  req.set(http::field::host, "127.0.0.1");
  if (!o.key.empty()) req.set(http::field::authorization, "Bearer " + o.key);
  http::write(stream, req);
  beast::flat_buffer buffer;
  http::response<http::string_body> res;
  http::read(stream, buffer, res);
  if (res.result_int() != 200) throw std::runtime_error("GET /config: " + res.body());
  return Json::parse(res.body())["cameras"].get<std::vector<std::string>>();
}

void run_client(const Options& o, const std::string& image_b64, const std::vector<std::string>& cameras, int client,
                ClientStats& stats) {
  net::io_context ioc;
  beast::tcp_stream stream(ioc);
  stream.connect(net::ip::tcp::endpoint(net::ip::make_address("127.0.0.1"), o.port));
  Json state = Json::array();
  for (const auto& v : split(o.state)) state.push_back(std::stod(v));
  Json images = Json::object();
  for (const auto& c : cameras)
    if (c.find("empty_camera_") == std::string::npos) images[c] = image_b64;
  beast::flat_buffer buffer;
  for (int i = 0; i < o.requests; ++i) {
    const Json body = {{"instruction", o.instruction},
                       {"state", state},
                       {"images", images},
                       {"seed", uint64_t(client) * 100000 + uint64_t(i)}};
    http::request<http::string_body> req{http::verb::post, "/act", 11};
    req.set(http::field::host, "127.0.0.1");
    req.set(http::field::content_type, "application/json");
    if (!o.key.empty()) req.set(http::field::authorization, "Bearer " + o.key);
    req.body() = body.dump();
    req.prepare_payload();
    const auto t0 = Clock::now();
    http::write(stream, req);
    http::response_parser<http::string_body> parser;
    parser.body_limit(64 * 1024 * 1024);
    http::read(stream, buffer, parser);
    const double ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
    const auto& res = parser.get();
    if (res.result_int() != 200) {
      ++stats.errors;
      continue;
    }
    stats.latencies_ms.push_back(ms);
    stats.batch_sum += Json::parse(res.body())["batch_size"].get<double>();
  }
}

double percentile(std::vector<double> v, double p) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const double idx = p / 100.0 * double(v.size() - 1);
  const auto lo = std::size_t(idx);
  const auto hi = std::min(lo + 1, v.size() - 1);
  return v[lo] + (v[hi] - v[lo]) * (idx - double(lo));
}

}  // namespace

int main(int argc, char** argv) try {
  Options o;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string flag = argv[i], value = argv[i + 1];
    if (flag == "--port") o.port = uint16_t(std::stoi(value));
    else if (flag == "--clients") {
      o.clients.clear();
      for (const auto& c : split(value)) o.clients.push_back(std::stoi(c));
    } else if (flag == "--requests") o.requests = std::stoi(value);
    else if (flag == "--image") o.image = value;
    else if (flag == "--state") o.state = value;
    else if (flag == "--key") o.key = value;
    else {
      std::fprintf(stderr, "unknown flag %s\n", flag.c_str());
      return 2;
    }
  }
  if (o.image.empty()) o.image = std::string(TETHER_SOURCE_DIR_BENCH) + "/models/demo/sample.png";
  std::ifstream in(o.image, std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), {});
  if (bytes.empty()) {
    std::fprintf(stderr, "cannot read %s\n", o.image.c_str());
    return 2;
  }
  const std::string image_b64 = tether::serve::base64_encode(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size());

  const std::vector<std::string> cameras = fetch_cameras(o);
  std::printf("| clients | requests | throughput (req/s) | p50 (ms) | p95 (ms) | p99 (ms) | mean batch | errors |\n");
  std::printf("|---:|---:|---:|---:|---:|---:|---:|---:|\n");
  std::fflush(stdout);
  for (int n : o.clients) {
    std::vector<ClientStats> stats(static_cast<std::size_t>(n));
    std::vector<std::thread> threads;
    const auto t0 = Clock::now();
    for (int c = 0; c < n; ++c) threads.emplace_back([&, c] { run_client(o, image_b64, cameras, c, stats[std::size_t(c)]); });
    for (auto& t : threads) t.join();
    const double secs = std::chrono::duration<double>(Clock::now() - t0).count();
    std::vector<double> all;
    double batch_sum = 0;
    int errors = 0;
    for (const auto& s : stats) {
      all.insert(all.end(), s.latencies_ms.begin(), s.latencies_ms.end());
      batch_sum += s.batch_sum;
      errors += s.errors;
    }
    std::printf("| %d | %zu | %.1f | %.1f | %.1f | %.1f | %.2f | %d |\n", n, all.size(), double(all.size()) / secs,
                percentile(all, 50), percentile(all, 95), percentile(all, 99),
                all.empty() ? 0.0 : batch_sum / double(all.size()), errors);
    std::fflush(stdout);
  }
  return 0;
} catch (const std::exception& e) {
  std::fprintf(stderr, "error: %s\n", e.what());
  return 2;
}
