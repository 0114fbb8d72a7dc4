// The HTTP/1.1 action server: binds first, loads and warms the model in the background (health says so), then
// answers /act through the batching scheduler. Limits, auth, request ids, metrics, graceful shutdown.
// How serve/ is split (session, router, /act pipeline, model host, wedge metrics): docs/serve-pipeline.md.
// Error codes beyond the /act body's (see act_request.h): 401 unauthorized, 404 not_found, 405 method_not_allowed,
// 408 request_timeout, 413 body_too_large, 431 header_too_large (Beast reports header_limit; answered 431, never
// 400), 400 bad_request (malformed HTTP), 500 inference_failed, 500 internal_error (a bug caught per request),
// 503 queue_full / not_ready (both with Retry-After: 1), 503 circuit_open (Retry-After: seconds until the half-open
// probe), 504 deadline_exceeded (--deadline-ms passed with no cached chunk or fallback to answer with). A read that times out closes the connection unanswered:
// the socket is already shut by then.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "serve/auth.h"
#include "serve/engine.h"
#include "serve/model_host.h"
#include "serve/request_id.h"
#include "serve/server_options.h"

namespace tether::serve {

class Server {
 public:
  using EngineLoader = serve::EngineLoader;
  Server(ServerOptions options, EngineLoader loader);
  // One host per embodiment (serve/model_host.h's ModelHosts), loaded in order; the first is the default.
  Server(ServerOptions options, std::vector<HostLoader> hosts);
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
  // The transports besides HTTP that start() bound, by name (Transport::name), in start order.
  std::vector<std::pair<std::string, uint16_t>> transport_ports() const;
  HealthState health() const;
  ModelHosts& hosts();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace tether::serve
