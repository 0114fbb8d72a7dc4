// The server's frame: binding, the accept loop, signals and graceful shutdown, and the wiring of the model host,
// the /act pipeline, the router and the HTTP sessions (each in its own file).
#include "serve/server.h"

#include <boost/asio.hpp>
#include <chrono>
#include <cstdio>
#include <thread>
#include <vector>

#include "core/error.h"
#include "serve/act_pipeline.h"
#include "serve/host_address.h"
#include "serve/http_session.h"
#include "serve/metrics.h"
#include "serve/router.h"
#include "serve/transport.h"

namespace tether::serve {

namespace net = boost::asio;
using tcp = net::ip::tcp;
using Clock = std::chrono::steady_clock;

struct Server::Impl {
  ServerOptions opts;
  net::io_context ioc;
  // The acceptor is touched by the accept loop and by shutdown: both run on this strand, never concurrently.
  net::strand<net::io_context::executor_type> accept_strand = net::make_strand(ioc);
  tcp::acceptor acceptor{accept_strand};
  net::signal_set signals{accept_strand};
  Metrics metrics;
  ModelHosts hosts;
  ActPipeline pipeline;
  Router router;
  HttpSessions sessions;
  std::vector<std::unique_ptr<Transport>> transports;  // besides HTTP, as the options ask
  std::thread load_thread;
  std::atomic<bool> draining{false}, stop_requested{false};
  uint16_t bound_port = 0;
  std::vector<std::pair<std::string, uint16_t>> transport_ports;

  Impl(ServerOptions o, std::vector<HostLoader> loaders)
      : opts(std::move(o)),
        metrics(TETHER_VERSION, ""),
        hosts(std::move(loaders), opts.batch, opts.wedges, metrics),
        pipeline(opts, hosts, metrics),
        router(opts, hosts, metrics, pipeline),
        sessions(opts, router, metrics),
        transports(make_transports({opts, hosts, metrics, pipeline, ioc,
                                     [this] { net::post(accept_strand, [this] { begin_shutdown(); }); }})) {}

  int in_flight() const {
    int n = sessions.in_flight();
    for (const auto& t : transports) n += t->in_flight();
    return n;
  }

  void stop_transports() {
    for (auto& t : transports) t->stop();
  }

  void load_model() {
    if (!hosts.load()) net::post(accept_strand, [this] { begin_shutdown(); });
  }

  void spawn_session(tcp::socket socket) {
    // Request/response traffic: Nagle would hold a response's last segment back until the client's delayed ACK.
    boost::system::error_code ec;
    socket.set_option(tcp::no_delay(true), ec);
    auto executor = socket.get_executor();
    net::co_spawn(executor, sessions.serve(std::move(socket)), net::detached);
  }

  net::awaitable<void> accept_loop() {
    for (;;) {
      boost::system::error_code ec;
      // Each connection gets its own strand: the stream's timeout timer and its I/O completions never run at once
      // on two I/O threads (beast::tcp_stream is not thread-safe).
      tcp::socket socket =
          co_await acceptor.async_accept(net::make_strand(ioc), net::redirect_error(net::use_awaitable, ec));
      if (ec) {
        if (!acceptor.is_open()) co_return;
        // E.g. out of file descriptors: keep serving the connections we have and retry shortly, without spinning.
        net::steady_timer pause(accept_strand, std::chrono::milliseconds(50));
        co_await pause.async_wait(net::redirect_error(net::use_awaitable, ec));
        continue;
      }
      spawn_session(std::move(socket));
    }
  }

  void begin_shutdown() {
    if (draining.exchange(true)) return;
    sessions.begin_draining();
    for (auto& t : transports) t->begin_draining();
    boost::system::error_code ec;
    // Connections the kernel has already completed were made before the signal: take them, then stop listening.
    if (acceptor.is_open()) {
      acceptor.non_blocking(true, ec);
      for (int i = 0; i < 4096 && !ec; ++i) {
        tcp::socket socket(net::make_strand(ioc));
        acceptor.accept(socket, ec);
        if (!ec) spawn_session(std::move(socket));
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
      if (in_flight() > 0) idle_since = Clock::now();
      else if (Clock::now() - idle_since >= kQuiet) break;
      timer.expires_after(std::chrono::milliseconds(10));
      boost::system::error_code ec;
      co_await timer.async_wait(net::redirect_error(net::use_awaitable, ec));
    }
    if (in_flight() > 0)
      std::fprintf(stderr, "tether serve: shutdown timeout: %d request(s) still in flight\n", in_flight());
    ioc.stop();
  }
};

Server::Server(ServerOptions options, EngineLoader loader)
    : Server(std::move(options), std::vector<HostLoader>{{"", std::move(loader)}}) {}

Server::Server(ServerOptions options, std::vector<HostLoader> hosts)
    : impl_(std::make_unique<Impl>(std::move(options), std::move(hosts))) {}

Server::~Server() {
  impl_->stop_transports();
  if (impl_->load_thread.joinable()) impl_->load_thread.join();
  impl_->hosts.stop();
}

uint16_t Server::start() {
  auto& m = *impl_;
  boost::system::error_code ec;
  // A name such as "localhost": its first address.
  const tcp::endpoint endpoint(net::ip::make_address(resolve_host(m.opts.host).front()), m.opts.port);
  m.acceptor.open(endpoint.protocol(), ec);
  if (!ec) m.acceptor.set_option(net::socket_base::reuse_address(true), ec);
  if (!ec) m.acceptor.bind(endpoint, ec);
  if (!ec) m.acceptor.listen(net::socket_base::max_listen_connections, ec);
  if (ec)
    throw Error(ErrorCode::io, "cannot listen on " + m.opts.host + ":" + std::to_string(m.opts.port) + ": " + ec.message());
  m.bound_port = m.acceptor.local_endpoint().port();
  for (auto& t : m.transports) {
    try {
      m.transport_ports.emplace_back(t->name(), t->start());
    } catch (...) {
      m.stop_transports();
      throw;
    }
  }
  m.load_thread = std::thread([&m] { m.load_model(); });
  return m.bound_port;
}

void Server::run(bool handle_signals) {
  auto& m = *impl_;
  if (handle_signals) {
    m.signals.add(SIGINT);
    m.signals.add(SIGTERM);
    m.signals.async_wait([&m](const boost::system::error_code& ec, int sig) {
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
  m.stop_transports();
  if (m.load_thread.joinable()) m.load_thread.join();
  m.hosts.stop();
  if (m.hosts.load_error()) std::rethrow_exception(m.hosts.load_error());
}

void Server::stop() {
  impl_->stop_requested = true;
  net::post(impl_->accept_strand, [m = impl_.get()] { m->begin_shutdown(); });
}

uint16_t Server::port() const { return impl_->bound_port; }

std::vector<std::pair<std::string, uint16_t>> Server::transport_ports() const { return impl_->transport_ports; }

HealthState Server::health() const { return impl_->hosts.health(); }

ModelHosts& Server::hosts() { return impl_->hosts; }

}  // namespace tether::serve
