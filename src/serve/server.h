// The HTTP/1.1 action server: binds first, loads and warms the model in the background (health says so), then
// answers /act through the batching scheduler. Limits, auth, request ids, metrics, graceful shutdown.
// Error codes beyond the /act body's (see act_request.h): 401 unauthorized, 404 not_found, 405 method_not_allowed,
// 408 request_timeout, 413 body_too_large, 431 header_too_large (Beast reports header_limit; answered 431, never
// 400), 400 bad_request (malformed HTTP), 500 inference_failed, 500 internal_error (a bug caught per request),
// 503 queue_full / not_ready (both with Retry-After: 1), 503 circuit_open (Retry-After: seconds until the half-open
// probe), 504 deadline_exceeded (--deadline-ms passed with no cached chunk or fallback to answer with). A read that times out closes the connection unanswered:
// the socket is already shut by then.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "runtime/batcher.h"
#include "runtime/wedges.h"
#include "serve/engine.h"

namespace tether::serve {

// Every limit is named here with its default; `tether serve` exposes each as a flag.
struct ServerOptions {
  std::string host = "127.0.0.1";
  uint16_t port = 8000;  // 0: the OS picks a free port (see Server::port)
  std::string api_key;   // empty: /act and /config are open
  runtime::BatcherOptions batch;
  std::size_t max_body_bytes = 16 * 1024 * 1024;  // larger bodies: 413 body_too_large
  std::size_t max_header_bytes = 16 * 1024;       // larger headers: 431 header_too_large
  int read_timeout_ms = 10000;      // a request (or an idle keep-alive gap) taking longer: connection closed
  int write_timeout_ms = 10000;     // a response the client does not take in time: connection closed
  int request_timeout_ms = 30000;   // a request still queued after this: 408 request_timeout
  int shutdown_timeout_ms = 10000;  // in-flight requests get this long after SIGTERM/SIGINT
  int threads = 2;                  // I/O threads (inference runs on the batcher's worker)
  runtime::WedgeOptions wedges;     // safety wedges, episodes and trace recording (all off by default)
};

// The model's life cycle as /health reports it. `degraded`: the warm-up or the last few forward passes failed.
enum class HealthState { loading, warming, ready, degraded, failed, circuit_open };
const char* health_state_name(HealthState s);

class Server {
 public:
  using EngineLoader = std::function<Engine()>;
  Server(ServerOptions options, EngineLoader loader);
  ~Server();
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  // Binds the socket (throws tether::Error(io) naming the address when it cannot) and starts loading the model on
  // a background thread. Returns the bound port.
  uint16_t start();
  // Serves until stop() or SIGTERM/SIGINT (when `handle_signals`), then drains in-flight requests up to
  // shutdown_timeout_ms. Rethrows the loader's exception if the model could not be loaded.
  void run(bool handle_signals = true);
  // Thread-safe; begins the graceful shutdown that run() completes.
  void stop();

  uint16_t port() const;
  HealthState health() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Accepts a client-supplied request id only if it is 1..128 characters of [A-Za-z0-9._:-].
bool valid_request_id(const std::string& id);
// Constant-time in the length of `expected`: how long it takes says nothing about where `given` differs.
bool keys_equal(const std::string& given, const std::string& expected);
// A default noise seed from a request id (FNV-1a), so a logged id reproduces the request's noise.
uint64_t seed_from_request_id(const std::string& id);

}  // namespace tether::serve
