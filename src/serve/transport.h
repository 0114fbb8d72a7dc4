// A way into the action server besides HTTP: openpi's WebSocket, GR00T's ZMQ, Tether's ZMQ. Each turns its wire
// format into an ActInput, runs it through the one ActPipeline (so the same scheduler, wedges, API key, limits,
// traces and metrics apply) and turns the ActResponse into its reply. The Server owns them: it starts each after
// binding HTTP, stops them from taking new requests when it drains, and waits for their in-flight requests.
#pragma once

#include <boost/asio/io_context.hpp>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "serve/act_pipeline.h"
#include "serve/metrics.h"
#include "serve/model_host.h"
#include "serve/server_options.h"

namespace tether::serve {

// What a transport may use; everything outlives it.
struct TransportContext {
  const ServerOptions& options;
  ModelHosts& hosts;  // one per embodiment served; requests are routed by the pipeline (ActInput::embodiment)
  Metrics& metrics;
  ActPipeline& pipeline;
  boost::asio::io_context& ioc;  // the server's I/O threads: pipeline.run is awaited here
  std::function<void()> request_shutdown = {};  // a graceful stop, as SIGTERM (GR00T's kill endpoint)
};

class Transport {
 public:
  virtual ~Transport() = default;
  // As metrics and traces name it (RequestContext::transport).
  virtual const char* name() const = 0;
  // Binds its socket (throws tether::Error(io) naming the address) and starts serving. Returns the bound port.
  virtual uint16_t start() = 0;
  // Takes no new requests from now on; those in flight are answered.
  virtual void begin_draining() = 0;
  // Requests received and not yet answered.
  virtual int in_flight() const = 0;
  // Closes every socket and joins its threads; idempotent (the server calls it after draining, and on a failed start).
  virtual void stop() = 0;
};

// The transports the options ask for (a port given), not yet started.
std::vector<std::unique_ptr<Transport>> make_transports(const TransportContext& ctx);

}  // namespace tether::serve
