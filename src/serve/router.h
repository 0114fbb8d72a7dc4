// Routes an HTTP request to its endpoint: /act (through the transport-neutral ActPipeline), /health, /ready,
// /live, /config (behind the API key) and /metrics; every failure becomes a JSON error with its stable code.
#pragma once

#include <boost/asio/awaitable.hpp>
#include <chrono>

#include "serve/act_pipeline.h"
#include "serve/http_message.h"
#include "serve/kserve_endpoints.h"
#include "serve/metrics.h"
#include "serve/model_host.h"
#include "serve/server_options.h"

namespace tether::serve {

class Router {
 public:
  Router(const ServerOptions& options, ModelHosts& hosts, Metrics& metrics, ActPipeline& pipeline);

  // Runs one request to a response and counts it in tether_requests_total; never throws.
  boost::asio::awaitable<HttpResponse> handle(const HttpRequest& req, std::chrono::steady_clock::time_point received);

  // The bodies of /health and /config.
  Json health_json(HealthState s) const;
  // `host`'s configuration, with the embodiments served.
  Json config_json(const ModelHost& host) const;

 private:
  boost::asio::awaitable<HttpResponse> route(const HttpRequest& req, const std::string& request_id);

  const ServerOptions& opts_;
  ModelHosts& hosts_;
  Metrics& metrics_;
  ActPipeline& pipeline_;
  KServeEndpoints kserve_;  // /v2: the Open Inference Protocol
};

}  // namespace tether::serve
