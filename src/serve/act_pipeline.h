// The /act pipeline, independent of any transport: auth, readiness, the body limit, parsing, every safety wedge
// in order (runtime/wedges.h), inference under the deadline, the fallback, the guard, the trace line and the
// metrics. HTTP (and later ZMQ or WebSocket) only turn bytes into a call of run() and its ActResponse into bytes.
#pragma once

#include <boost/asio/any_io_executor.hpp>
#include <boost/asio/awaitable.hpp>
#include <boost/asio/thread_pool.hpp>
#include <chrono>
#include <memory>
#include <string>
#include <string_view>

#include "core/json_util.h"
#include "runtime/fallback_client.h"
#include "serve/act_trace.h"
#include "serve/metrics.h"
#include "serve/model_host.h"
#include "serve/server_options.h"

namespace tether::serve {

// What a transport knows about a request besides its body.
struct RequestContext {
  std::string request_id;  // chosen by the transport (the client's when valid, else request_id_or_new's)
  std::string api_key;     // the key the client presented, however its transport carries it; empty: none
  std::chrono::steady_clock::time_point received;  // when the request's first bytes were read: deadlines start here
  // Forwarded by another server's fallback client (runtime::kFallbackMarkerHeader): answered locally, never
  // forwarded again.
  bool from_fallback = false;
};

// The answer in transport-neutral form. HTTP sends `status` as the status line and `body` as JSON, with
// Retry-After: `retry_after_s` on a 503.
struct ActResponse {
  int status = 200;
  Json body;              // the /act answer, or {"error": {"code", "message"}} (see error_body)
  int retry_after_s = 1;  // meaningful with 503
  bool ok() const { return status == 200; }
};

class ActPipeline {
 public:
  ActPipeline(const ServerOptions& options, ModelHost& host, Metrics& metrics);
  ~ActPipeline();
  ActPipeline(const ActPipeline&) = delete;
  ActPipeline& operator=(const ActPipeline&) = delete;

  // Runs one /act request to its answer; never throws. Counts it in tether_requests_total{endpoint="/act"}.
  // `body` and `ctx` must outlive the awaitable (await it at once). Awaits the batcher and the fallback without
  // blocking the calling executor's thread.
  boost::asio::awaitable<ActResponse> run(std::string_view body, const RequestContext& ctx);

 private:
  struct Act;
  struct InferenceWait;
  struct Inference;

  boost::asio::awaitable<ActResponse> traced(std::string_view body, const RequestContext& ctx);
  boost::asio::awaitable<ActResponse> answer(std::string_view body, const RequestContext& ctx, ActTrace& trace);
  Act parse(std::string_view body, const RequestContext& ctx, ActTrace& trace);
  boost::asio::awaitable<void> admit(Act& a, std::string_view body, const RequestContext& ctx);
  void try_skip(Act& a);
  boost::asio::awaitable<Inference> infer(Act& a, const RequestContext& ctx);
  boost::asio::awaitable<void> recover(Act& a, Inference& inference, std::string_view body, const RequestContext& ctx,
                                       ActTrace& trace);
  ActResponse respond(Act& a, const RequestContext& ctx, ActTrace& trace);

  std::shared_ptr<InferenceWait> start_inference(const boost::asio::any_io_executor& ex, Act& a,
                                                 runtime::Clock::time_point observed,
                                                 runtime::Clock::time_point batch_deadline);
  boost::asio::awaitable<void> call_fallback(Act& a, std::string_view body, const std::string& request_id);

  const ServerOptions& opts_;
  ModelHost& host_;
  Metrics& metrics_;
  std::unique_ptr<runtime::FallbackClient> fallback_;  // null without --cloud-fallback
  // Fallback calls block in libcurl: they run here, never on an I/O thread. Declared last: joined first.
  std::unique_ptr<boost::asio::thread_pool> fallback_pool_;
};

}  // namespace tether::serve
