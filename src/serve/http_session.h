// HTTP/1.1 connections: one coroutine per connection (keep-alive loop) reading requests under the header, body and
// time limits, answering limit violations itself (413, 431, 400) and everything else through the Router.
#pragma once

#include <atomic>
#include <boost/asio/awaitable.hpp>
#include <boost/asio/ip/tcp.hpp>

#include "serve/metrics.h"
#include "serve/router.h"
#include "serve/server_options.h"

namespace tether::serve {

class HttpSessions {
 public:
  HttpSessions(const ServerOptions& options, Router& router, Metrics& metrics);

  // Serves one connection until the client closes it, a limit or timeout ends it, or draining stops keep-alive.
  // Never throws: a bug in the connection code drops that connection only.
  boost::asio::awaitable<void> serve(boost::asio::ip::tcp::socket socket);

  // From now on every response closes its connection.
  void begin_draining() { draining_ = true; }
  // Requests whose header has been read and whose response is not yet written.
  int in_flight() const { return in_flight_.load(); }

 private:
  boost::asio::awaitable<void> session(boost::asio::ip::tcp::socket socket);

  const ServerOptions& opts_;
  Router& router_;
  Metrics& metrics_;
  std::atomic<bool> draining_{false};
  std::atomic<int> in_flight_{0};
};

}  // namespace tether::serve
