// Beast/Asio HTTP server: one coroutine per connection (keep-alive loop), routes, auth, JSON errors with stable
// codes; /act awaits the batcher without blocking an I/O thread. Nothing a client sends may crash the process:
// every request runs inside a catch-all that answers 500.
#include "serve/server.h"

#include <boost/asio.hpp>
#include <boost/beast.hpp>
#include <chrono>
#include <cstdio>
#include <mutex>
#include <random>
#include <thread>

#include "core/error.h"
#include "core/json_util.h"
#include "serve/act_request.h"
#include "serve/http_error.h"
#include "serve/metrics.h"

namespace tether::serve {

namespace net = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
using tcp = net::ip::tcp;
using Clock = std::chrono::steady_clock;
using Request = http::request<http::string_body>;
using Response = http::response<http::string_body>;

const char* health_state_name(HealthState s) {
  switch (s) {
    case HealthState::loading: return "loading";
    case HealthState::warming: return "warming";
    case HealthState::ready: return "ready";
    case HealthState::degraded: return "degraded";
    case HealthState::failed: return "failed";
  }
  return "unknown";
}

bool valid_request_id(const std::string& id) {
  if (id.empty() || id.size() > 128) return false;
  for (char c : id)
    if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '_' || c == ':' || c == '-')) return false;
  return true;
}

bool keys_equal(const std::string& given, const std::string& expected) {
  // Every byte of `expected` is visited whatever `given` holds; a length mismatch is folded into the same result.
  unsigned char diff = given.size() == expected.size() ? 0 : 1;
  for (std::size_t i = 0; i < expected.size(); ++i) {
    const unsigned char g = i < given.size() ? static_cast<unsigned char>(given[i]) : 0;
    diff |= static_cast<unsigned char>(g ^ static_cast<unsigned char>(expected[i]));
  }
  return diff == 0;
}

uint64_t seed_from_request_id(const std::string& id) {
  uint64_t h = 1469598103934665603ull;
  for (char c : id) {
    h ^= static_cast<unsigned char>(c);
    h *= 1099511628211ull;
  }
  return h;
}

namespace {

// Consecutive failed forward passes after which /health reports degraded (one bad batch is not a sick server).
constexpr int kDegradedAfterFailures = 3;

double ms_since(Clock::time_point t) { return std::chrono::duration<double, std::milli>(Clock::now() - t).count(); }

// Fresh ids: a per-process random base plus a counter, mixed so consecutive ids do not look sequential.
std::string generate_request_id() {
  static const uint64_t base = [] {
    std::random_device rd;
    return (uint64_t(rd()) << 32) ^ rd();
  }();
  static std::atomic<uint64_t> counter{0};
  uint64_t z = base + 0x9e3779b97f4a7c15ull * (++counter);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  z ^= z >> 31;
  char buf[17];
  std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(z));
  return buf;
}

std::string header(const Request& req, std::string_view name) {
  auto it = req.find(name);
  return it == req.end() ? std::string() : std::string(it->value());
}

std::string request_id_of(const Request& req) {
  for (const char* name : {"X-Tether-Request-ID", "X-Request-ID"}) {
    const std::string id = header(req, name);
    if (valid_request_id(id)) return id;
  }
  return generate_request_id();
}

const char* kKnownPaths[] = {"/act", "/health", "/ready", "/live", "/config", "/metrics"};

std::string endpoint_label(std::string_view target) {
  const std::string_view path = target.substr(0, target.find('?'));
  for (const char* p : kKnownPaths)
    if (path == p) return p;
  return "other";
}

// Completes the awaiting coroutine on its own executor once the batcher has run (or refused) the request.
template <typename Token>
auto async_predict(runtime::Batcher& batcher, policy::Observation obs, Clock::time_point deadline, Token&& token) {
  return net::async_initiate<Token, void(std::exception_ptr, runtime::BatchResult)>(
      [&batcher, deadline](auto handler, policy::Observation o) {
        auto ex = net::get_associated_executor(handler);
        auto h = std::make_shared<decltype(handler)>(std::move(handler));
        try {
          batcher.submit(std::move(o), deadline, [h, ex](std::exception_ptr e, runtime::BatchResult r) {
            // The handler is moved out and run on the coroutine's executor, so the worker's copy of `h` (released
            // whenever the worker gets to it) owns nothing of the coroutine.
            net::post(ex, [h, e = std::move(e), r = std::move(r)]() mutable {
              auto handler = std::move(*h);
              handler(std::move(e), std::move(r));
            });
          });
        } catch (...) {
          net::post(ex, [h, e = std::current_exception()]() mutable {
            auto handler = std::move(*h);
            handler(std::move(e), runtime::BatchResult{});
          });
        }
      },
      token, std::move(obs));
}

// Counts a request from its header until its response is written (or the connection fails).
class InFlight {
 public:
  InFlight(std::atomic<int>& n, bool active) : n_(active ? &n : nullptr) {
    if (n_) ++*n_;
  }
  ~InFlight() {
    if (n_) --*n_;
  }
  InFlight(const InFlight&) = delete;
  InFlight& operator=(const InFlight&) = delete;

 private:
  std::atomic<int>* n_;
};

}  // namespace

struct Server::Impl {
  ServerOptions opts;
  EngineLoader loader;
  net::io_context ioc;
  // The acceptor is touched by the accept loop and by shutdown: both run on this strand, never concurrently.
  net::strand<net::io_context::executor_type> accept_strand = net::make_strand(ioc);
  tcp::acceptor acceptor{accept_strand};
  net::signal_set signals{accept_strand};
  Metrics metrics;

  std::atomic<HealthState> state{HealthState::loading};
  // Written once by the loader thread before `state` leaves `loading` (release), read after (acquire).
  std::unique_ptr<Engine> engine;
  std::unique_ptr<runtime::Batcher> batcher;
  std::exception_ptr load_error;
  std::thread load_thread;

  std::atomic<bool> draining{false}, stop_requested{false};
  std::atomic<int> in_flight{0};
  uint16_t bound_port = 0;

  Impl(ServerOptions o, EngineLoader l) : opts(std::move(o)), loader(std::move(l)), metrics(TETHER_VERSION, "") {}

  HealthState health() const {
    const HealthState s = state.load(std::memory_order_acquire);
    if (s != HealthState::ready && s != HealthState::degraded) return s;
    const int failures = batcher->consecutive_failures();
    if (failures >= kDegradedAfterFailures) return HealthState::degraded;
    // A failed warm-up is forgiven by the first forward pass that succeeds after it.
    if (s == HealthState::degraded && failures == 0 && batcher->batches_run() > 1) return HealthState::ready;
    return s;
  }
  // Engine and batcher exist (and are safe to read) once loading has finished successfully.
  bool loaded() const {
    const HealthState s = state.load(std::memory_order_acquire);
    return s == HealthState::warming || s == HealthState::ready || s == HealthState::degraded;
  }
  bool serving() const {
    const HealthState s = health();
    return s == HealthState::ready || s == HealthState::degraded;
  }

  void load_model() {
    try {
      auto e = std::make_unique<Engine>(loader());
      auto b = std::make_unique<runtime::Batcher>(e->predict, opts.batch);
      metrics.set_gemm(e->gemm);
      engine = std::move(e);
      batcher = std::move(b);
      state.store(HealthState::warming, std::memory_order_release);
      std::fprintf(stderr, "tether serve: model loaded (%s, %s); warming up\n", engine->spec.family.c_str(),
                   engine->model_hash.c_str());
      for (const auto& w : engine->load_warnings) std::fprintf(stderr, "tether serve: warning: %s\n", w.c_str());
      try {
        const auto t0 = Clock::now();
        batcher->submit(policy::synthetic_observation(engine->spec), Clock::time_point::max()).get();
        std::fprintf(stderr, "tether serve: ready (warm-up %.1f ms)\n", ms_since(t0));
        state.store(HealthState::ready, std::memory_order_release);
      } catch (const std::exception& ex) {
        std::fprintf(stderr, "tether serve: warm-up inference failed: %s\n", ex.what());
        state.store(HealthState::degraded, std::memory_order_release);
      }
      metrics.set_model_ready(state.load() == HealthState::ready);
    } catch (...) {
      load_error = std::current_exception();
      state.store(HealthState::failed, std::memory_order_release);
      net::post(accept_strand, [this] { begin_shutdown(); });
    }
  }

  // ---- responses ----

  Response make_response(const Request& req, http::status status, const std::string& body,
                         const std::string& request_id, const char* content_type = "application/json") {
    Response res{status, req.version()};
    res.set(http::field::server, "tether/" TETHER_VERSION);
    res.set(http::field::content_type, content_type);
    res.set("X-Tether-Request-ID", request_id);
    res.body() = body;
    res.prepare_payload();
    return res;
  }

  Response error_response(const Request& req, int status, const std::string& code, const std::string& message,
                          const std::string& request_id) {
    const Json body = {{"error", {{"code", code}, {"message", message}}}};
    Response res = make_response(req, http::status(status), body.dump(-1, ' ', false, Json::error_handler_t::replace),
                                 request_id);
    if (status == 503) res.set(http::field::retry_after, "1");
    return res;
  }

  Response json_response(const Request& req, int status, const Json& body, const std::string& request_id) {
    Response res = make_response(req, http::status(status), body.dump(-1, ' ', false, Json::error_handler_t::replace),
                                 request_id);
    if (status == 503) res.set(http::field::retry_after, "1");
    return res;
  }

  void require_auth(const Request& req) {
    if (opts.api_key.empty()) return;
    std::string given = header(req, "X-Tether-Key");
    if (given.empty()) {
      const std::string auth = header(req, "Authorization");
      if (auth.size() > 7 && (auth.compare(0, 7, "Bearer ") == 0 || auth.compare(0, 7, "bearer ") == 0))
        given = auth.substr(7);
    }
    if (given.empty() || !keys_equal(given, opts.api_key))
      throw HttpError(401, "unauthorized", given.empty() ? "an API key is required (Authorization: Bearer <key> or X-Tether-Key)"
                                                         : "the API key is not valid");
  }

  void require_ready() {
    if (!serving())
      throw HttpError(503, "not_ready", std::string("the model is not ready (") + health_state_name(health()) + ")");
  }

  Json health_json(HealthState s) const {
    const bool ok = s == HealthState::ready;
    return {{"status", ok ? "ok" : "unavailable"},
            {"state", health_state_name(s)},
            {"model_hash", loaded() ? Json(engine->model_hash) : Json(nullptr)}};
  }

  Json config_json() const {
    const auto& s = engine->spec;
    return {{"family", s.family},
            {"cameras", s.cameras},
            {"state_dim", s.state_dim},
            {"action_dim", s.action_dim},
            {"chunk_size", s.chunk_size},
            {"num_steps", s.num_steps},
            {"normalization", engine->normalization},
            {"weights_dtype", s.weights_dtype},
            {"model_hash", engine->model_hash},
            {"inference_mode", {{"backend", engine->backend}, {"precision", engine->precision}, {"gemm", engine->gemm}}},
            {"load_warnings", engine->load_warnings},
            {"limits",
             {{"max_batch", opts.batch.max_batch},
              {"batch_timeout_ms", opts.batch.batch_timeout_ms},
              {"max_queue", opts.batch.max_queue},
              {"max_body_bytes", opts.max_body_bytes},
              {"max_header_bytes", opts.max_header_bytes},
              {"read_timeout_ms", opts.read_timeout_ms},
              {"write_timeout_ms", opts.write_timeout_ms},
              {"request_timeout_ms", opts.request_timeout_ms},
              {"shutdown_timeout_ms", opts.shutdown_timeout_ms}}}};
  }

  net::awaitable<Response> act(const Request& req, const std::string& request_id, Clock::time_point received) {
    require_auth(req);
    require_ready();
    const auto t_parse = Clock::now();
    ActRequest parsed = parse_act_request(req.body(), engine->spec);
    parsed.observation.seed = parsed.seed ? *parsed.seed : seed_from_request_id(request_id);
    const double parse_ms = ms_since(t_parse);

    runtime::BatchResult r;
    try {
      r = co_await async_predict(*batcher, std::move(parsed.observation),
                                 received + std::chrono::milliseconds(opts.request_timeout_ms), net::use_awaitable);
    } catch (const runtime::BatchError& e) {
      switch (e.kind()) {
        case runtime::BatchError::Kind::queue_full: throw HttpError(503, "queue_full", e.what());
        case runtime::BatchError::Kind::deadline_exceeded: throw HttpError(408, "request_timeout", e.what());
        case runtime::BatchError::Kind::stopped: throw HttpError(503, "not_ready", e.what());
        case runtime::BatchError::Kind::inference_failed: throw HttpError(500, "inference_failed", e.what());
      }
      throw;
    }

    const auto& c = r.chunk;
    Json actions = Json::array();
    for (int64_t row = 0; row < c.chunk_size; ++row)
      actions.push_back(std::vector<float>(c.actions.begin() + row * c.action_dim,
                                           c.actions.begin() + (row + 1) * c.action_dim));
    const double preprocess_ms = parse_ms + r.normalize_ms + r.timings.preprocess_ms;
    const double total_ms = ms_since(received);
    const std::pair<const char*, double> stages[] = {
        {"total", total_ms},           {"queue", r.queue_ms},           {"preprocess", preprocess_ms},
        {"vision", r.timings.vision_ms}, {"prefix", r.timings.prefix_ms}, {"denoise", r.timings.denoise_ms},
        {"postprocess", r.postprocess_ms}};
    Json latency = Json::object();
    for (const auto& [name, ms] : stages) {
      latency[name] = ms;
      metrics.observe_stage(name, ms / 1000.0);
    }
    if (r.index_in_batch == 0) metrics.observe_batch_size(r.batch_size);
    const Json body = {
        {"actions", std::move(actions)},
        {"num_actions", c.chunk_size},
        {"action_dim", c.action_dim},
        {"latency_ms", latency},
        {"inference_mode", {{"backend", engine->backend}, {"precision", engine->precision}, {"gemm", engine->gemm}}},
        {"model_hash", engine->model_hash},
        {"request_id", request_id},
        {"episode_id", parsed.episode_id ? Json(*parsed.episode_id) : Json(nullptr)},
        {"batch_size", r.batch_size},
        {"warnings", c.warnings}};
    co_return json_response(req, 200, body, request_id);
  }

  net::awaitable<Response> route(const Request& req, const std::string& request_id, Clock::time_point received) {
    const std::string path(req.target().substr(0, req.target().find('?')));
    const bool is_get = req.method() == http::verb::get;
    auto require_method = [&](bool ok, const char* allow) {
      if (!ok) throw HttpError(405, "method_not_allowed", path + " accepts " + allow + " only");
    };
    if (path == "/act") {
      require_method(req.method() == http::verb::post, "POST");
      co_return co_await act(req, request_id, received);
    }
    if (path == "/health") {
      require_method(is_get, "GET");
      const HealthState s = health();
      co_return json_response(req, s == HealthState::ready ? 200 : 503, health_json(s), request_id);
    }
    if (path == "/ready") {
      require_method(is_get, "GET");
      const bool ready = health() == HealthState::ready;
      co_return json_response(req, ready ? 200 : 503, {{"ready", ready}}, request_id);
    }
    if (path == "/live") {
      require_method(is_get, "GET");
      co_return json_response(req, 200, {{"live", true}}, request_id);
    }
    if (path == "/config") {
      require_method(is_get, "GET");
      require_auth(req);
      if (!loaded())
        throw HttpError(503, "not_ready", "the model is still loading");
      co_return json_response(req, 200, config_json(), request_id);
    }
    if (path == "/metrics") {
      require_method(is_get, "GET");
      metrics.set_queue_depth(loaded() ? batcher->queue_depth() : 0);
      metrics.set_model_ready(health() == HealthState::ready);
      co_return make_response(req, http::status::ok, metrics.render(), request_id,
                              "text/plain; version=0.0.4; charset=utf-8");
    }
    throw HttpError(404, "not_found", "no endpoint " + path + " (try /act, /health, /ready, /live, /config, /metrics)");
  }

  // Runs one request to a response; never throws.
  net::awaitable<Response> handle(const Request& req, Clock::time_point received) {
    const std::string request_id = request_id_of(req);
    int status = 500;
    std::string code = "internal_error", message;
    try {
      Response res = co_await route(req, request_id, received);
      metrics.count_request(endpoint_label(req.target()), res.result_int());
      co_return res;
    } catch (const HttpError& e) {
      status = e.status();
      code = e.code();
      message = e.what();
    } catch (const std::exception& e) {
      message = std::string("internal error: ") + e.what();
    } catch (...) {
      message = "internal error";
    }
    metrics.count_request(endpoint_label(req.target()), status);
    co_return error_response(req, status, code, message, request_id);
  }

  // ---- connections ----

  // After an error response on a request whose body was not read: stop sending, then read and discard what the
  // client still sends for a moment, so the response is not lost to a TCP reset.
  net::awaitable<void> linger_close(beast::tcp_stream& stream) {
    beast::error_code ec;
    stream.socket().shutdown(tcp::socket::shutdown_send, ec);
    stream.expires_after(std::chrono::seconds(2));
    std::vector<char> sink(64 * 1024);
    std::size_t discarded = 0;
    while (discarded < opts.max_body_bytes * 4) {
      const std::size_t n =
          co_await stream.async_read_some(net::buffer(sink), net::redirect_error(net::use_awaitable, ec));
      if (ec) break;
      discarded += n;
    }
    stream.socket().close(ec);
  }

  net::awaitable<void> write_and_close(beast::tcp_stream& stream, Response res) {
    res.keep_alive(false);
    beast::error_code ec;
    stream.expires_after(std::chrono::milliseconds(opts.write_timeout_ms));
    co_await http::async_write(stream, res, net::redirect_error(net::use_awaitable, ec));
    if (!ec) co_await linger_close(stream);
  }

  net::awaitable<void> session(tcp::socket socket) {
    beast::tcp_stream stream(std::move(socket));
    beast::flat_buffer buffer;
    beast::error_code ec;
    for (;;) {
      http::request_parser<http::string_body> parser;
      parser.header_limit(std::uint32_t(std::min<std::size_t>(opts.max_header_bytes, UINT32_MAX)));
      parser.body_limit(opts.max_body_bytes);
      stream.expires_after(std::chrono::milliseconds(opts.read_timeout_ms));
      co_await http::async_read_header(stream, buffer, parser, net::redirect_error(net::use_awaitable, ec));
      const auto received = Clock::now();
      InFlight guard(in_flight, !ec);
      if (!ec && parser.get()[http::field::expect] == "100-continue") {
        // curl and others wait for this before sending a large body.
        http::response<http::empty_body> cont{http::status::continue_, parser.get().version()};
        co_await http::async_write(stream, cont, net::redirect_error(net::use_awaitable, ec));
      }
      if (!ec && !parser.is_done())
        co_await http::async_read(stream, buffer, parser, net::redirect_error(net::use_awaitable, ec));
      if (ec) {
        // Beast reports an over-long header as header_limit: answered 431, as the contract documents.
        // The fields read so far are in the message even when the error came before the header "completed"
        // (Beast checks Content-Length against the body limit while finishing the header), so the client's
        // request id still applies.
        Request partial = parser.get();
        if (partial.version() == 0) partial.version(11);
        const std::string rid = request_id_of(partial);
        if (ec == http::error::body_limit) {
          metrics.count_request(endpoint_label(partial.target()), 413);
          co_await write_and_close(stream, error_response(partial, 413, "body_too_large",
                                                          "the body exceeds " + std::to_string(opts.max_body_bytes) +
                                                              " bytes (--max-body-bytes)", rid));
        } else if (ec == http::error::header_limit) {
          metrics.count_request("other", 431);
          co_await write_and_close(stream, error_response(partial, 431, "header_too_large",
                                                          "the request header exceeds " +
                                                              std::to_string(opts.max_header_bytes) +
                                                              " bytes (--max-header-bytes)", rid));
        } else if (&ec.category() == &http::make_error_code(http::error::bad_target).category() &&
                   ec != http::error::end_of_stream && ec != http::error::partial_message) {
          metrics.count_request("other", 400);
          co_await write_and_close(stream, error_response(partial, 400, "bad_request",
                                                          std::string("malformed HTTP request: ") + ec.message(), rid));
        }
        // Otherwise: the client closed, the connection broke, or a read timed out (the stream is closed then).
        break;
      }
      Request req = parser.release();
      Response res = co_await handle(req, received);
      const bool keep = req.keep_alive() && !draining.load();
      res.keep_alive(keep);
      stream.expires_after(std::chrono::milliseconds(opts.write_timeout_ms));
      co_await http::async_write(stream, res, net::redirect_error(net::use_awaitable, ec));
      if (ec || !keep) break;
    }
    stream.socket().shutdown(tcp::socket::shutdown_both, ec);
    stream.socket().close(ec);
  }

  // Requests already answer every failure; this catch-all keeps a bug in the connection code from ending the process.
  net::awaitable<void> guarded_session(tcp::socket socket) {
    try {
      co_await session(std::move(socket));
    } catch (const std::exception& e) {
      std::fprintf(stderr, "tether serve: connection dropped: %s\n", e.what());
    }
  }

  net::awaitable<void> accept_loop() {
    for (;;) {
      beast::error_code ec;
      // Each connection gets its own strand: the stream's timeout timer and its I/O completions never run at once
      // on two I/O threads (beast::tcp_stream is not thread-safe).
      tcp::socket socket = co_await acceptor.async_accept(net::make_strand(ioc), net::redirect_error(net::use_awaitable, ec));
      if (ec) {
        if (!acceptor.is_open()) co_return;
        // E.g. out of file descriptors: keep serving the connections we have and retry shortly, without spinning.
        net::steady_timer pause(accept_strand, std::chrono::milliseconds(50));
        co_await pause.async_wait(net::redirect_error(net::use_awaitable, ec));
        continue;
      }
      auto executor = socket.get_executor();
      net::co_spawn(executor, guarded_session(std::move(socket)), net::detached);
    }
  }

  void begin_shutdown() {
    if (draining.exchange(true)) return;
    beast::error_code ec;
    // Connections the kernel has already completed were made before the signal: take them, then stop listening.
    if (acceptor.is_open()) {
      acceptor.non_blocking(true, ec);
      for (int i = 0; i < 4096 && !ec; ++i) {
        tcp::socket socket(net::make_strand(ioc));
        acceptor.accept(socket, ec);
        if (!ec) {
          auto executor = socket.get_executor();
          net::co_spawn(executor, guarded_session(std::move(socket)), net::detached);
        }
      }
      ec.clear();
    }
    acceptor.close(ec);
    signals.cancel(ec);
    net::co_spawn(ioc, drain(), net::detached);
  }

  // Waits for in-flight requests (up to the shutdown timeout), then stops the I/O loop.
  net::awaitable<void> drain() {
    const auto until = Clock::now() + std::chrono::milliseconds(opts.shutdown_timeout_ms);
    net::steady_timer timer(ioc);
    // A request counts as in flight once its header is read; one whose bytes are still being read is caught by
    // requiring the count to stay at zero for a short quiet period.
    constexpr auto kQuiet = std::chrono::milliseconds(100);
    auto idle_since = Clock::now();
    while (Clock::now() < until) {
      if (in_flight.load() > 0) idle_since = Clock::now();
      else if (Clock::now() - idle_since >= kQuiet) break;
      timer.expires_after(std::chrono::milliseconds(10));
      beast::error_code ec;
      co_await timer.async_wait(net::redirect_error(net::use_awaitable, ec));
    }
    if (in_flight.load() > 0)
      std::fprintf(stderr, "tether serve: shutdown timeout: %d request(s) still in flight\n", in_flight.load());
    ioc.stop();
  }
};

Server::Server(ServerOptions options, EngineLoader loader)
    : impl_(std::make_unique<Impl>(std::move(options), std::move(loader))) {}

Server::~Server() {
  if (impl_->load_thread.joinable()) impl_->load_thread.join();
  if (impl_->batcher) impl_->batcher->stop();
}

uint16_t Server::start() {
  auto& m = *impl_;
  beast::error_code ec;
  auto address = net::ip::make_address(m.opts.host, ec);
  if (ec) {  // a name such as "localhost": its first address
    tcp::resolver resolver(m.ioc);
    const auto results = resolver.resolve(m.opts.host, "", ec);
    if (ec || results.empty())
      throw Error(ErrorCode::invalid_argument, "--host '" + m.opts.host + "' is neither an IP address nor a known name");
    address = results.begin()->endpoint().address();
  }
  const tcp::endpoint endpoint(address, m.opts.port);
  m.acceptor.open(endpoint.protocol(), ec);
  if (!ec) m.acceptor.set_option(net::socket_base::reuse_address(true), ec);
  if (!ec) m.acceptor.bind(endpoint, ec);
  if (!ec) m.acceptor.listen(net::socket_base::max_listen_connections, ec);
  if (ec)
    throw Error(ErrorCode::io, "cannot listen on " + m.opts.host + ":" + std::to_string(m.opts.port) + ": " + ec.message());
  m.bound_port = m.acceptor.local_endpoint().port();
  m.load_thread = std::thread([&m] { m.load_model(); });
  return m.bound_port;
}

void Server::run(bool handle_signals) {
  auto& m = *impl_;
  if (handle_signals) {
    m.signals.add(SIGINT);
    m.signals.add(SIGTERM);
    m.signals.async_wait([&m](const beast::error_code& ec, int sig) {
      if (ec) return;
      std::fprintf(stderr, "tether serve: %s received, finishing in-flight requests\n", sig == SIGINT ? "SIGINT" : "SIGTERM");
      net::post(m.accept_strand, [&m] { m.begin_shutdown(); });
    });
  }
  if (m.stop_requested.load()) net::post(m.accept_strand, [&m] { m.begin_shutdown(); });
  net::co_spawn(m.accept_strand, m.accept_loop(), net::detached);
  std::vector<std::thread> threads;
  for (int i = 1; i < std::max(1, m.opts.threads); ++i) threads.emplace_back([&m] { m.ioc.run(); });
  m.ioc.run();
  for (auto& t : threads) t.join();
  if (m.load_thread.joinable()) m.load_thread.join();
  if (m.batcher) m.batcher->stop();
  if (m.load_error) std::rethrow_exception(m.load_error);
}

void Server::stop() {
  impl_->stop_requested = true;
  net::post(impl_->accept_strand, [m = impl_.get()] { m->begin_shutdown(); });
}

uint16_t Server::port() const { return impl_->bound_port; }

HealthState Server::health() const { return impl_->health(); }

}  // namespace tether::serve
