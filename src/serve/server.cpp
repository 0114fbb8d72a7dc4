// Beast/Asio HTTP server: one coroutine per connection (keep-alive loop), routes, auth, JSON errors with stable
// codes; /act awaits the batcher without blocking an I/O thread. Nothing a client sends may crash the process:
// every request runs inside a catch-all that answers 500.
#include "serve/server.h"

#include <boost/asio.hpp>
#include <boost/beast.hpp>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <cstdio>
#include <mutex>
#include <random>
#include <thread>

#include "core/error.h"
#include "core/hash.h"
#include "hub/http.h"
#include "serve/base64.h"
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
    case HealthState::circuit_open: return "circuit_open";
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

bool all_finite(const std::vector<float>& v) {
  for (float x : v)
    if (!std::isfinite(x)) return false;
  return true;
}

std::string format_ms(double ms) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g ms", ms);
  return buf;
}

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

  runtime::Wedges wedges;
  // Fallback calls block in libcurl: they run here, never on an I/O thread.
  net::thread_pool fallback_pool{2};

  Impl(ServerOptions o, EngineLoader l)
      : opts(std::move(o)), loader(std::move(l)), metrics(TETHER_VERSION, ""), wedges(opts.wedges) {}

  // /health's view: the model's state, overridden by an open circuit.
  HealthState health() const {
    const HealthState s = model_state();
    if ((s == HealthState::ready || s == HealthState::degraded) &&
        wedges.breaker().state() != runtime::CircuitBreaker::State::closed)
      return HealthState::circuit_open;
    return s;
  }

  HealthState model_state() const {
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
    const HealthState s = model_state();
    return s == HealthState::ready || s == HealthState::degraded;
  }

  void load_model() {
    try {
      auto e = std::make_unique<Engine>(loader());
      wedges.bind_model(e->spec, e->actions_normalized);
      runtime::PredictFn predict = e->predict;
      if (const double delay = opts.wedges.inject_latency_ms; delay > 0)
        predict = [predict, delay](const std::vector<policy::Observation>& batch) {
          std::this_thread::sleep_for(std::chrono::duration<double, std::milli>(delay));
          return predict(batch);
        };
      if (const std::string fault = opts.wedges.inject_failure_file; !fault.empty())
        predict = [predict, fault](const std::vector<policy::Observation>& batch) {
          if (std::filesystem::exists(fault))
            throw Error(ErrorCode::internal, "injected failure (--inject-failure-file " + fault + " exists)");
          return predict(batch);
        };
      auto b = std::make_unique<runtime::Batcher>(std::move(predict), opts.batch);
      metrics.set_gemm(e->gemm);
      metrics.declare_stages(e->spec.stages);
      register_wedge_metrics();
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
                          const std::string& request_id, int retry_after_s = 1) {
    const Json body = {{"error", {{"code", code}, {"message", message}}}};
    Response res = make_response(req, http::status(status), body.dump(-1, ' ', false, Json::error_handler_t::replace),
                                 request_id);
    if (status == 503) res.set(http::field::retry_after, std::to_string(retry_after_s));
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
    Json h = {{"status", ok ? "ok" : "unavailable"},
              {"state", health_state_name(s)},
              {"model_hash", loaded() ? Json(engine->model_hash) : Json(nullptr)}};
    if (wedges.breaker().enabled()) {
      const auto& b = wedges.breaker();
      h["circuit"] = {{"state", runtime::circuit_state_name(b.state())},
                      {"consecutive_failures", b.consecutive_failures()},
                      {"times_opened", b.times_opened()},
                      {"retry_after_s", b.retry_after_s()}};
    }
    return h;
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
            {"inference_mode", {{"backend", engine->backend}, {"precision", engine->precision}, {"compute", engine->compute}, {"gemm", engine->gemm}}},
            {"load_warnings", engine->load_warnings},
            {"wedges", wedges.config_json()},
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

  // ---- /act: the wedge pipeline (order documented in runtime/wedges.h) ----

  // Local inference as one request waits for it: completed on the request's executor, or abandoned at the deadline
  // (the forward pass then still finishes and refreshes the episode's last good chunk).
  struct InferenceWait {
    explicit InferenceWait(const net::any_io_executor& ex) : timer(ex) {}
    net::steady_timer timer;
    bool done = false;
    std::exception_ptr error;
    runtime::BatchResult result;
  };

  std::shared_ptr<InferenceWait> start_inference(const net::any_io_executor& ex, policy::Observation obs,
                                                 std::shared_ptr<runtime::Episode> ep, Clock::time_point observed,
                                                 std::vector<float> normalized_state, bool probe,
                                                 Clock::time_point batch_deadline) {
    auto wait = std::make_shared<InferenceWait>(ex);
    // The similarity skip compares later observations with this one: keep it when that wedge is on.
    std::shared_ptr<policy::Observation> reference;
    if (wedges.skip_enabled()) reference = std::make_shared<policy::Observation>(obs);
    auto done = [this, ex, wait, ep, observed, reference, state = std::move(normalized_state), probe](
                    std::exception_ptr e, runtime::BatchResult r) {
      if (!e && !all_finite(r.chunk.actions)) {
        wedges.breaker().record_failure();  // a broken model, even though it did not throw
      } else if (!e) {
        wedges.breaker().record_success();
        wedges.on_model_chunk(*ep, r.chunk.actions, observed, reference.get(), state);
      } else {
        bool model_failed = false;
        try {
          std::rethrow_exception(e);
        } catch (const runtime::BatchError& be) {
          model_failed = be.kind() == runtime::BatchError::Kind::inference_failed;
        } catch (...) {
          model_failed = true;
        }
        if (model_failed) wedges.breaker().record_failure();
        else if (probe) wedges.breaker().abandon_probe();
      }
      net::post(ex, [wait, e = std::move(e), r = std::move(r)]() mutable {
        wait->done = true;
        wait->error = std::move(e);
        wait->result = std::move(r);
        wait->timer.cancel();
      });
    };
    try {
      batcher->submit(std::move(obs), batch_deadline, done);
    } catch (...) {
      done(std::current_exception(), runtime::BatchResult{});
    }
    return wait;
  }

  // Forwards the request body to the fallback server; the actions it answers with, or nullopt (why in `report`).
  net::awaitable<std::optional<std::vector<float>>> call_fallback(const std::string& body, const std::string& request_id,
                                                                  int64_t& rows, runtime::WedgeReport& report) {
    const auto& w = opts.wedges;
    hub::HttpRequest fr;
    fr.method = "POST";
    fr.url = w.cloud_fallback;
    if (!fr.url.empty() && fr.url.back() == '/') fr.url.pop_back();
    fr.url += "/act";
    fr.body = body;
    fr.timeout_ms = w.fallback_timeout_ms;
    fr.headers = {"Content-Type: application/json", "X-Tether-Request-ID: " + request_id, "X-Tether-Fallback: 1"};
    if (!w.fallback_api_key.empty()) fr.headers.push_back("Authorization: Bearer " + w.fallback_api_key);
    // The blocking libcurl call runs on the fallback pool; co_spawn brings the result back to this coroutine's strand.
    // The awaitable is a named local: GCC 12 can destroy temporaries of a co_await operand twice.
    auto request = std::make_shared<const hub::HttpRequest>(std::move(fr));
    auto perform = net::co_spawn(
        fallback_pool, [request]() -> net::awaitable<hub::HttpResult> { co_return hub::HttpClient().perform(*request); },
        net::use_awaitable);
    const hub::HttpResult res = co_await std::move(perform);
    auto fail = [&](const std::string& why) -> std::optional<std::vector<float>> {
      report.fallback_error = why;
      metrics.add_counter("tether_fallback_total", "Requests forwarded to the cloud fallback, by outcome.", 1,
                          "outcome=\"failure\"");
      return std::nullopt;
    };
    if (res.failure != hub::TransportFailure::none) co_return fail("fallback unreachable: " + res.error);
    if (res.response.status != 200)
      co_return fail("fallback answered HTTP " + std::to_string(res.response.status));
    Json j = Json::parse(res.response.body, nullptr, false);
    const int64_t dim = engine->spec.action_dim;
    if (j.is_discarded() || !j.is_object() || !j.contains("actions") || !j["actions"].is_array() || j["actions"].empty())
      co_return fail("fallback answered without an actions array");
    std::vector<float> actions;
    for (const auto& row : j["actions"]) {
      if (!row.is_array() || int64_t(row.size()) != dim)
        co_return fail("fallback actions do not have " + std::to_string(dim) + " values per row");
      for (const auto& v : row) {
        if (!v.is_number()) co_return fail("fallback actions hold a non-number");
        actions.push_back(float(v.get<double>()));
      }
    }
    rows = int64_t(j["actions"].size());
    report.fallback_used = true;
    report.source = runtime::ActionSource::fallback;
    metrics.add_counter("tether_fallback_total", "Requests forwarded to the cloud fallback, by outcome.", 1,
                        "outcome=\"success\"");
    co_return actions;
  }

  // Inputs of a request as the trace keeps them: images by hash unless --record-images full.
  Json trace_inputs(const policy::Observation& obs) const {
    Json images = Json::object();
    for (const auto& [camera, img] : obs.images) {
      Json i = {{"width", img.width}, {"height", img.height},
                {"sha256", sha256_hex(std::string(img.rgb.begin(), img.rgb.end()))}};
      // The raw-image form /act accepts, so a recorded request can be replayed as it was.
      if (opts.wedges.record_images_full)
        i["data"] = {{"data", base64_encode(img.rgb.data(), img.rgb.size())}, {"shape", {img.height, img.width, 3}}};
      images[camera] = std::move(i);
    }
    return {{"state", obs.state}, {"images", std::move(images)}, {"seed", obs.seed}};
  }

  // Everything /act learned about a request, for its trace line (filled as the pipeline advances).
  struct ActTrace {
    std::string episode_id, task;
    Json inputs, actions, latency = Json::object(), wedges = Json::object();
    bool has_episode = false;
  };

  void record_trace(const ActTrace& t, const std::string& request_id, int status, const std::string& code,
                    const std::string& message) {
    runtime::TraceRecorder* rec = wedges.recorder();
    if (!rec) return;
    Json line = {{"request_id", request_id},
                 {"episode_id", t.has_episode ? Json(t.episode_id) : Json(nullptr)},
                 {"task", t.task},
                 {"model", engine ? engine->model_name : ""},
                 {"model_hash", engine ? engine->model_hash : ""},
                 {"status", status == 200 ? "success" : "failed"},
                 {"http_status", status},
                 {"error", code.empty() ? Json(nullptr) : Json{{"code", code}, {"message", message}}},
                 {"inputs", t.inputs.is_null() ? Json(nullptr) : t.inputs},
                 {"actions", t.actions.is_null() ? Json(nullptr) : t.actions},
                 {"latency_ms", t.latency},
                 {"wedges", t.wedges}};
    if (!rec->append(std::move(line)))
      metrics.add_counter("tether_trace_write_errors_total", "Trace lines that could not be written.");
  }

  void count_wedges(const runtime::WedgeReport& r) {
    if (r.guard.clamped) metrics.add_counter("tether_guard_clamped_total", "Responses the action guard changed.");
    for (const auto& v : r.guard.violations)
      metrics.add_counter("tether_guard_violations_total", "Values the action guard clamped, by joint and limit.", 1,
                          "joint=\"" + escape_label(v.joint) + "\",limit=\"" + escape_label(v.limit) + "\"");
    if (r.skipped) metrics.add_counter("tether_action_skip_total", "Requests answered from the cached chunk (similarity).");
    if (r.source == runtime::ActionSource::last_good)
      metrics.add_counter("tether_last_good_chunk_total", "Deadline misses answered with the last good chunk.");
    if (r.denoise_steps_used > 0) {
      metrics.add_counter("tether_denoise_steps_total", "Denoise steps run (adaptive steps).", r.denoise_steps_used);
      metrics.add_counter("tether_denoise_runs_total", "Forward passes counted in tether_denoise_steps_total.");
    }
    if (r.rtc_applied) metrics.add_counter("tether_rtc_total", "Requests denoised with real-time chunking guidance.");
  }

  // Enabled wedges appear in /metrics from the start, at zero.
  void register_wedge_metrics() {
    const auto& w = opts.wedges;
    if (wedges.guard_enabled()) metrics.add_counter("tether_guard_clamped_total", "Responses the action guard changed.", 0);
    if (w.deadline_ms > 0)
      metrics.add_counter("tether_deadline_exceeded_total", "Requests that missed --deadline-ms.", 0);
    if (wedges.skip_enabled())
      metrics.add_counter("tether_action_skip_total", "Requests answered from the cached chunk (similarity).", 0);
    if (w.adaptive_threshold > 0)
      metrics.add_counter("tether_denoise_steps_total", "Denoise steps run (adaptive steps).", 0);
    if (w.rtc) metrics.add_counter("tether_rtc_total", "Requests denoised with real-time chunking guidance.", 0);
    if (!w.cloud_fallback.empty())
      for (const char* outcome : {"success", "failure"})
        metrics.add_counter("tether_fallback_total", "Requests forwarded to the cloud fallback, by outcome.", 0,
                            std::string("outcome=\"") + outcome + "\"");
    if (wedges.breaker().enabled())
      metrics.add_counter("tether_circuit_rejected_total", "Requests refused while the circuit was open.", 0);
  }

  // Gauges read at scrape time.
  void refresh_wedge_gauges() {
    const auto& w = opts.wedges;
    if (wedges.breaker().enabled()) {
      const auto st = wedges.breaker().state();
      metrics.set_gauge("tether_circuit_open", "1 while the circuit breaker refuses local inference (open or half-open).",
                        st == runtime::CircuitBreaker::State::closed ? 0 : 1);
      metrics.set_gauge("tether_circuit_opened_total", "Times the circuit breaker opened.",
                        double(wedges.breaker().times_opened()));
      metrics.set_gauge("tether_consecutive_failures", "Consecutive failed inferences.",
                        wedges.breaker().consecutive_failures());
    }
    if (w.inject_latency_ms > 0)
      metrics.set_gauge("tether_injected_latency_ms", "Synthetic delay added to every forward pass.", w.inject_latency_ms);
    metrics.set_gauge("tether_episodes", "Episodes the server holds state for.", double(wedges.episodes().size()));
    if (const auto* rec = wedges.recorder()) {
      metrics.set_gauge("tether_trace_lines_total", "Trace lines written since start.", double(rec->lines_written()));
      metrics.set_gauge("tether_trace_write_errors", "Trace lines lost to I/O errors since start.",
                        double(rec->write_errors()));
    }
  }

  net::awaitable<Response> act(const Request& req, const std::string& request_id, Clock::time_point received) {
    require_auth(req);
    require_ready();
    ActTrace trace;
    try {
      Response res = co_await act_pipeline(req, request_id, received, trace);
      record_trace(trace, request_id, 200, "", "");
      co_return res;
    } catch (const HttpError& e) {
      trace.latency["total"] = ms_since(received);
      record_trace(trace, request_id, e.status(), e.code(), e.what());
      throw;
    } catch (const std::exception& e) {
      trace.latency["total"] = ms_since(received);
      record_trace(trace, request_id, 500, "internal_error", std::string("internal error: ") + e.what());
      throw;
    }
  }

  net::awaitable<Response> act_pipeline(const Request& req, const std::string& request_id, Clock::time_point received,
                                        ActTrace& trace) {
    const auto& w = opts.wedges;
    const auto& spec = engine->spec;
    const auto t_parse = Clock::now();
    ActRequest parsed = parse_act_request(req.body(), spec);
    policy::Observation& obs = parsed.observation;
    obs.seed = parsed.seed ? *parsed.seed : seed_from_request_id(request_id);
    trace.task = obs.instruction;
    trace.has_episode = parsed.episode_id.has_value();
    trace.episode_id = parsed.episode_id.value_or("");
    if (wedges.recorder()) trace.inputs = trace_inputs(obs);
    if (parsed.rtc && !w.rtc)
      throw HttpError(400, "invalid_field", "rtc: this server runs without --rtc (real-time chunking is off)");
    const double parse_ms = ms_since(t_parse);

    auto ep = wedges.episodes().get(trace.episode_id);
    const std::vector<float> state = obs.state;
    // Only the similarity skip measures in normalised units: nothing to compute without it.
    std::vector<float> normalized_state;
    if (wedges.skip_enabled()) normalized_state = engine->normalize_state ? engine->normalize_state(state) : state;
    runtime::WedgeReport report;
    std::optional<std::vector<float>> actions;
    int64_t rows = spec.chunk_size;
    std::optional<runtime::BatchResult> ran;  // set when this request's own forward pass answered
    const bool may_forward = !w.cloud_fallback.empty() && header(req, "X-Tether-Fallback").empty();

    // 1. Circuit breaker.
    const auto admission = wedges.breaker().admit();
    bool probe = admission == runtime::CircuitBreaker::Admission::probe;
    if (admission == runtime::CircuitBreaker::Admission::reject) {
      metrics.add_counter("tether_circuit_rejected_total", "Requests refused while the circuit was open.");
      if (may_forward) actions = co_await call_fallback(req.body(), request_id, rows, report);
      if (!actions) {
        const int retry = wedges.breaker().retry_after_s();
        throw HttpError(503, "circuit_open",
                        "local inference failed " + std::to_string(w.max_consecutive_crashes) +
                            " times in a row; the circuit is open (a probe request is let through in " +
                            std::to_string(retry) + " s)" +
                            (report.fallback_error.empty() ? "" : "; " + report.fallback_error),
                        retry);
      }
    }
    // 2. Similarity skip.
    if (!actions) {
      actions = wedges.try_skip(*ep, obs, normalized_state, report);
      if (actions && probe) {
        wedges.breaker().abandon_probe();
        probe = false;
      }
    }
    // 3. Inference under the deadline.
    if (!actions) {
      obs.adaptive_threshold = w.adaptive_threshold;
      if (parsed.rtc) {
        policy::Observation::Rtc rtc;
        rtc.prev_actions = std::move(parsed.rtc->prev_actions);
        rtc.inference_delay = parsed.rtc->inference_delay;
        rtc.execution_horizon = w.rtc_execution_horizon;
        rtc.max_guidance_weight = w.rtc_max_guidance_weight;
        rtc.schedule = w.rtc_schedule;
        obs.rtc = std::move(rtc);
        report.rtc_applied = true;
      }
      const bool has_deadline = w.deadline_ms > 0;
      const auto deadline = has_deadline ? received + std::chrono::microseconds(int64_t(w.deadline_ms * 1000))
                                         : Clock::time_point::max();
      const auto batch_deadline =
          std::min(deadline, received + std::chrono::milliseconds(opts.request_timeout_ms));
      auto ex = co_await net::this_coro::executor;
      auto wait = start_inference(ex, std::move(obs), ep, received, normalized_state, probe, batch_deadline);
      if (!wait->done) {
        wait->timer.expires_at(deadline);
        beast::error_code ec;
        co_await wait->timer.async_wait(net::redirect_error(net::use_awaitable, ec));
      }
      std::optional<runtime::BatchError::Kind> failure;
      std::string failure_message;
      if (!wait->done) {
        failure = runtime::BatchError::Kind::deadline_exceeded;
      } else if (wait->error) {
        try {
          std::rethrow_exception(wait->error);
        } catch (const runtime::BatchError& e) {
          failure = e.kind();
          failure_message = e.what();
        } catch (const std::exception& e) {
          failure = runtime::BatchError::Kind::inference_failed;
          failure_message = e.what();
        }
      } else if (!all_finite(wait->result.chunk.actions)) {
        failure = runtime::BatchError::Kind::inference_failed;
        failure_message = "the model produced non-finite actions (NaN or Inf)";
      } else {
        ran = std::move(wait->result);
        actions = ran->chunk.actions;  // already mapped to the embodiment's range by on_model_chunk
        report.denoise_steps_used = ran->chunk.denoise_steps_used;
      }
      if (failure) {
        const bool missed = *failure == runtime::BatchError::Kind::deadline_exceeded && has_deadline;
        report.deadline_exceeded = missed;
        if (missed) metrics.add_counter("tether_deadline_exceeded_total", "Requests that missed --deadline-ms.");
        if (!missed) report.inference_error = failure_message;
        // 4. Cloud fallback, 5. last good chunk.
        if (may_forward) actions = co_await call_fallback(req.body(), request_id, rows, report);
        if (actions) wedges.on_fallback_chunk(*ep, *actions, rows, received);
        if (!actions && missed) actions = wedges.last_good(*ep, report);
        // A non-finite chunk with nothing better to send: the guard replaces each bad value with the last safe command.
        if (!actions && wait->done && !wait->error && wedges.guard_enabled()) {
          ran = std::move(wait->result);
          actions = ran->chunk.actions;
          wedges.map_output(*actions);
          report.denoise_steps_used = ran->chunk.denoise_steps_used;
        }
        if (!actions) {
          trace.wedges = wedges.response_fields(report);
          const std::string tail = report.fallback_error.empty() ? "" : "; " + report.fallback_error;
          switch (*failure) {
            case runtime::BatchError::Kind::queue_full: throw HttpError(503, "queue_full", failure_message + tail);
            case runtime::BatchError::Kind::stopped: throw HttpError(503, "not_ready", failure_message + tail);
            case runtime::BatchError::Kind::inference_failed:
              throw HttpError(500, "inference_failed", failure_message + tail);
            case runtime::BatchError::Kind::deadline_exceeded:
              if (missed)
                throw HttpError(504, "deadline_exceeded",
                                "inference did not finish within --deadline-ms " + format_ms(w.deadline_ms) +
                                    " and this episode has no earlier chunk to fall back on" + tail);
              throw HttpError(408, "request_timeout", failure_message + tail);
          }
        }
      }
    }

    // 7. Guard: last, whatever produced the actions.
    wedges.guard(*ep, *actions, rows, state, request_id, trace.episode_id, report);
    count_wedges(report);

    const int64_t dim = spec.action_dim;
    Json actions_json = Json::array();
    for (int64_t row = 0; row < rows; ++row)
      actions_json.push_back(std::vector<float>(actions->begin() + row * dim, actions->begin() + (row + 1) * dim));
    Json latency = Json::object();
    std::vector<std::pair<std::string, double>> stages = {{"total", ms_since(received)}};
    if (ran) {
      stages.emplace_back("queue", ran->queue_ms);
      // The model's stages in its order (ModelSpec::stages); the first also carries parsing and normalisation.
      for (std::size_t i = 0; i < spec.stages.size(); ++i)
        stages.emplace_back(spec.stages[i],
                            ran->timings.get(spec.stages[i]) + (i == 0 ? parse_ms + ran->normalize_ms : 0.0));
      stages.emplace_back("postprocess", ran->postprocess_ms);
      if (ran->index_in_batch == 0) metrics.observe_batch_size(ran->batch_size);
    }
    for (const auto& [name, ms] : stages) {
      latency[name] = ms;
      metrics.observe_stage(name, ms / 1000.0);
    }
    Json body = {
        {"actions", actions_json},
        {"num_actions", rows},
        {"action_dim", dim},
        {"latency_ms", latency},
        {"inference_mode", {{"backend", engine->backend}, {"precision", engine->precision}, {"compute", engine->compute}, {"gemm", engine->gemm}}},
        {"model_hash", engine->model_hash},
        {"request_id", request_id},
        {"episode_id", parsed.episode_id ? Json(*parsed.episode_id) : Json(nullptr)},
        {"batch_size", ran ? ran->batch_size : 0},
        {"warnings", ran ? ran->chunk.warnings : std::vector<std::string>{}}};
    const Json wedge_fields = wedges.response_fields(report);
    for (auto it = wedge_fields.begin(); it != wedge_fields.end(); ++it) body[it.key()] = it.value();
    trace.actions = std::move(actions_json);
    trace.latency = std::move(latency);
    trace.wedges = wedge_fields;
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
      Response res = json_response(req, s == HealthState::ready ? 200 : 503, health_json(s), request_id);
      if (s == HealthState::circuit_open)
        res.set(http::field::retry_after, std::to_string(std::max(1, wedges.breaker().retry_after_s())));
      co_return res;
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
      refresh_wedge_gauges();
      metrics.set_model_ready(health() == HealthState::ready);
      co_return make_response(req, http::status::ok, metrics.render(), request_id,
                              "text/plain; version=0.0.4; charset=utf-8");
    }
    throw HttpError(404, "not_found", "no endpoint " + path + " (try /act, /health, /ready, /live, /config, /metrics)");
  }

  // Runs one request to a response; never throws.
  net::awaitable<Response> handle(const Request& req, Clock::time_point received) {
    const std::string request_id = request_id_of(req);
    int status = 500, retry_after_s = 1;
    std::string code = "internal_error", message;
    try {
      Response res = co_await route(req, request_id, received);
      metrics.count_request(endpoint_label(req.target()), res.result_int());
      co_return res;
    } catch (const HttpError& e) {
      status = e.status();
      code = e.code();
      message = e.what();
      retry_after_s = e.retry_after_s();
    } catch (const std::exception& e) {
      message = std::string("internal error: ") + e.what();
    } catch (...) {
      message = "internal error";
    }
    metrics.count_request(endpoint_label(req.target()), status);
    co_return error_response(req, status, code, message, request_id, retry_after_s);
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
