// Framing of openpi's WebSocket policy protocol over Beast: the upgrade (with /healthz and the API key before it),
// the metadata frame, frames read under a size limit, one pipeline run per frame, and openpi's failure shape.
#include "serve/openpi_transport.h"

#include <atomic>
#include <boost/asio.hpp>
#include <boost/beast.hpp>
#include <boost/beast/websocket.hpp>
#include <chrono>
#include <cstdio>
#include <map>
#include <mutex>

#include "serve/auth.h"
#include "serve/host_address.h"
#include "serve/http_error.h"
#include "serve/http_message.h"
#include "serve/openpi_protocol.h"
#include "serve/request_id.h"

namespace tether::serve {

namespace net = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
using tcp = net::ip::tcp;
using Clock = std::chrono::steady_clock;
using Ws = websocket::stream<beast::tcp_stream>;

namespace {

// Pings are answered with pongs: more than this many in a second is a flood, and the connection is dropped.
constexpr int kMaxPingsPerSecond = 50;
// The upgrade request has no body; anything larger than a header is not an openpi client.
constexpr std::size_t kMaxUpgradeBodyBytes = 0;

double ms_between(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double, std::milli>(b - a).count();
}

}  // namespace

struct OpenpiConnection {
  explicit OpenpiConnection(beast::tcp_stream stream) : ws(std::move(stream)) {}
  Ws ws;
  // Touched only on the connection's strand.
  bool waiting = false;  // between frames: a drain may close it at once
  bool closing = false;
  int pings = 0;
  Clock::time_point ping_window;
};

struct OpenpiTransport::Shared {
  // Every layout is read here, so a bad mapping file fails at start-up.
  explicit Shared(const TransportContext& c)
      : ctx(c), layouts(openpi::load_layouts(c.options.openpi.layout)), accept_strand(net::make_strand(c.ioc)),
        acceptor(accept_strand) {
    for (const auto& [tag, layout] : c.options.openpi.layout_by_embodiment)
      own_layouts[tag] = openpi::load_layouts(layout);
  }

  TransportContext ctx;
  openpi::Layouts layouts;                             // every embodiment's without one of its own
  std::map<std::string, openpi::Layouts> own_layouts;  // by embodiment tag
  const openpi::Layouts& layouts_for(const std::string& embodiment) const {
    const auto it = own_layouts.find(embodiment);
    return it == own_layouts.end() ? layouts : it->second;
  }
  net::strand<net::io_context::executor_type> accept_strand;
  tcp::acceptor acceptor;
  std::atomic<bool> draining{false};
  std::atomic<int> in_flight{0};
  std::mutex mu;
  std::map<uint64_t, std::weak_ptr<OpenpiConnection>> connections;
  uint64_t next_id = 0;

  const ServerOptions& opts() const { return ctx.options; }
  std::size_t max_frame_bytes() const {
    return opts().openpi.max_frame_bytes ? opts().openpi.max_frame_bytes : opts().max_body_bytes;
  }
};

namespace {

using Shared = OpenpiTransport::Shared;

// Counts a frame from its last byte read to its reply written.
class InFlight {
 public:
  explicit InFlight(std::atomic<int>& n) : n_(n) { ++n_; }
  ~InFlight() { --n_; }
  InFlight(const InFlight&) = delete;
  InFlight& operator=(const InFlight&) = delete;

 private:
  std::atomic<int>& n_;
};

class Registration {
 public:
  Registration(Shared& s, const std::shared_ptr<OpenpiConnection>& c) : s_(s) {
    std::lock_guard lock(s_.mu);
    id_ = s_.next_id++;
    s_.connections[id_] = c;
  }
  ~Registration() {
    std::lock_guard lock(s_.mu);
    s_.connections.erase(id_);
  }
  Registration(const Registration&) = delete;
  Registration& operator=(const Registration&) = delete;

 private:
  Shared& s_;
  uint64_t id_ = 0;
};

// The key the upgrade carries: openpi_client's "Authorization: Api-Key <key>", or HTTP's Bearer / X-Tether-Key.
std::string presented_key(const HttpRequest& req) {
  const std::string auth = header(req, "Authorization");
  constexpr std::string_view kApiKey = "Api-Key ";
  if (auth.size() > kApiKey.size() && std::string_view(auth).substr(0, kApiKey.size()) == kApiKey)
    return auth.substr(kApiKey.size());
  return presented_api_key(req);
}

// Built outside any coroutine: GCC 12 mishandles some temporaries inside co_await expressions.
HttpResponse plain_response(const HttpRequest& req, http::status status, std::string body, const char* content_type,
                            int retry_after_s = 0) {
  HttpResponse res{status, req.version() ? req.version() : 11u};
  res.set(http::field::server, "tether/" TETHER_VERSION);
  res.set(http::field::content_type, content_type);
  if (status == http::status::upgrade_required) res.set(http::field::upgrade, "websocket");
  if (retry_after_s > 0) res.set(http::field::retry_after, std::to_string(retry_after_s));
  res.body() = std::move(body);
  res.keep_alive(false);
  res.prepare_payload();
  return res;
}

net::awaitable<void> send_and_close(beast::tcp_stream& stream, const HttpResponse& res, const ServerOptions& opts) {
  beast::error_code ec;
  stream.expires_after(std::chrono::milliseconds(opts.write_timeout_ms));
  co_await http::async_write(stream, res, net::redirect_error(net::use_awaitable, ec));
  stream.socket().shutdown(tcp::socket::shutdown_both, ec);
  stream.socket().close(ec);
}

std::string error_json(const std::string& code, const std::string& message) {
  return error_body(code, message).dump(-1, ' ', false, Json::error_handler_t::replace);
}

// A frame written under the write timeout: a client that stops reading loses its connection, nobody else waits.
net::awaitable<bool> write_frame(Ws& ws, std::string_view data, bool text, int timeout_ms) {
  beast::error_code ec;
  ws.text(text);
  beast::get_lowest_layer(ws).expires_after(std::chrono::milliseconds(timeout_ms));
  co_await ws.async_write(net::buffer(data.data(), data.size()), net::redirect_error(net::use_awaitable, ec));
  beast::get_lowest_layer(ws).expires_never();
  co_return !ec;
}

// openpi's failure shape: the reason as a text frame (WebsocketClientPolicy raises it), then a close frame.
net::awaitable<void> fail_connection(Ws& ws, OpenpiConnection& conn, const std::string& text, websocket::close_code code,
                                     const std::string& reason, const ServerOptions& opts) {
  conn.closing = true;
  if (!co_await write_frame(ws, text, true, opts.write_timeout_ms)) co_return;
  // A close reason holds at most 123 bytes (RFC 6455 5.5).
  const websocket::close_reason close(code, std::string_view(reason).substr(0, 123));
  beast::error_code ec;
  co_await ws.async_close(close, net::redirect_error(net::use_awaitable, ec));
}

// What the connection's embodiment (its upgrade's ?embodiment_tag=, else the server's default) is fed and answers.
Json metadata(const Shared& s, const ModelHost& host, const openpi::Layouts& layouts) {
  const Engine& engine = host.engine();
  const auto& spec = engine.spec;
  Json keys = Json::object();
  for (const auto& layout : layouts.candidates) {
    Json cams = Json::object();
    try {
      const auto cameras = openpi::resolve_cameras(layout, spec);
      for (std::size_t i = 0; i < cameras.size(); ++i)
        cams[layout.images[i].key] = cameras[i] ? Json(*cameras[i]) : Json(nullptr);
    } catch (const std::exception& e) {
      cams = e.what();
    }
    keys[layout.name] = std::move(cams);
  }
  return {{"server", "tether"},
          {"version", TETHER_VERSION},
          {"model", engine.model_name},
          {"family", spec.family},
          {"model_hash", engine.model_hash},
          {"action_horizon", spec.chunk_size},
          {"action_dim", host.wedges().action_dim()},
          {"state_dim", spec.state_dim},
          {"embodiment_tag", spec.embodiment.empty() ? Json(nullptr) : Json(spec.embodiment)},
          {"embodiments", s.ctx.hosts.embodiments()},
          {"layout", layouts.name},
          {"cameras", keys}};
}

std::string failure_text(const ActResponse& r, const std::string& request_id) {
  std::string code = "error", message;
  if (const auto e = r.body.find("error"); e != r.body.end() && e->is_object()) {
    code = e->value("code", code);
    message = e->value("message", "");
  }
  std::string text = "tether: " + std::to_string(r.status) + " " + code + ": " + message + " (request " + request_id + ")";
  if (r.status == 503) text += "; retry after " + std::to_string(r.retry_after_s) + " s";
  return text;
}

// One WebSocket connection from the upgrade to its close.
net::awaitable<void> websocket_session(std::shared_ptr<Shared> s, std::shared_ptr<OpenpiConnection> conn,
                                       HttpRequest req, std::string api_key, std::string embodiment) {
  const ServerOptions& opts = s->opts();
  Ws& ws = conn->ws;
  websocket::stream_base::timeout timeouts;
  timeouts.handshake_timeout = std::chrono::milliseconds(opts.read_timeout_ms);  // also bounds the close handshake
  timeouts.idle_timeout = opts.openpi.idle_timeout_ms > 0
                              ? websocket::stream_base::duration(std::chrono::milliseconds(opts.openpi.idle_timeout_ms))
                              : websocket::stream_base::none();
  timeouts.keep_alive_pings = true;
  ws.set_option(timeouts);
  ws.set_option(websocket::stream_base::decorator(
      [](websocket::response_type& res) { res.set(http::field::server, "tether/" TETHER_VERSION); }));
  ws.read_message_max(0);  // the frame limit is enforced below, so its refusal can say why
  ws.auto_fragment(false);
  ws.control_callback([c = conn.get(), &ws](websocket::frame_type kind, beast::string_view) {
    if (kind != websocket::frame_type::ping) return;
    const auto now = Clock::now();
    if (now - c->ping_window > std::chrono::seconds(1)) c->ping_window = now, c->pings = 0;
    if (++c->pings > kMaxPingsPerSecond) {
      beast::error_code ec;
      beast::get_lowest_layer(ws).socket().close(ec);  // the read in progress fails and ends the session
    }
  });
  beast::error_code ec;
  co_await ws.async_accept(req, net::redirect_error(net::use_awaitable, ec));
  if (ec) co_return;
  Registration registered(*s, conn);
  const ModelHost& host = s->ctx.hosts.route(embodiment);
  const openpi::Layouts& layouts = s->layouts_for(host.embodiment());  // the connection's robot's keys
  const std::string meta = openpi::encode_json(metadata(*s, host, layouts));
  if (!co_await write_frame(ws, meta, false, opts.write_timeout_ms)) co_return;

  const std::size_t limit = s->max_frame_bytes();
  std::optional<double> prev_total_ms;
  beast::flat_buffer frame;
  for (;;) {
    if (s->draining.load()) {
      co_await ws.async_close(websocket::close_reason(websocket::close_code::going_away, "server shutting down"),
                              net::redirect_error(net::use_awaitable, ec));
      co_return;
    }
    // openpi's total: from waiting for the frame to the reply sent.
    const auto wait_start = Clock::now();
    frame.clear();
    std::optional<Clock::time_point> received;
    bool too_big = false;
    conn->waiting = true;
    for (;;) {
      const std::size_t room = std::min<std::size_t>(limit + 1 - frame.size(), 1 << 20);
      co_await ws.async_read_some(frame, room, net::redirect_error(net::use_awaitable, ec));
      if (ec) break;
      if (!received) received = Clock::now(), conn->waiting = false;
      if (frame.size() > limit) {
        too_big = true;
        break;
      }
      if (ws.is_message_done()) break;
    }
    conn->waiting = false;
    if (ec) co_return;  // closed by the client, a drain, a timeout or a broken connection
    if (conn->closing) co_return;
    if (too_big) {
      InFlight counted(s->in_flight);
      const std::string why = "frame exceeds " + std::to_string(limit) + " bytes (--openpi-max-frame-bytes)";
      const std::string text = "tether: 413 frame_too_large: " + why;
      s->ctx.metrics.count_request("/act", 413, "openpi");
      co_await fail_connection(ws, *conn, text, websocket::close_code::too_big, why, opts);
      co_return;
    }
    InFlight counted(s->in_flight);
    RequestContext ctx;
    ctx.request_id = request_id_or_new({});
    ctx.api_key = api_key;
    ctx.received = *received;
    ctx.transport = "openpi";
    const auto data = frame.cdata();
    const std::string_view bytes(static_cast<const char*>(data.data()), data.size());
    ActInput input;
    input.wire_bytes = bytes.size();
    // A text frame is refused inside the pipeline too, so it is counted and traced like any bad frame.
    input.decode = [bytes, &layouts, binary = ws.got_binary()](const models::ModelSpec& m) {
      if (!binary) throw HttpError(400, "invalid_msgpack", "expected a binary msgpack frame, got a text frame");
      return openpi::decode_request(bytes, layouts, m);
    };
    input.act_json = [](const ActRequest& r) { return act_request_json(r); };
    input.embodiment = [&embodiment] { return embodiment; };
    const auto t0 = Clock::now();
    // The idle timer counts only while waiting for a frame: a long inference (the client waits) must not drop it.
    ws.set_option(websocket::stream_base::timeout{websocket::stream_base::none(), websocket::stream_base::none(), false});
    const ActResponse answer = co_await s->ctx.pipeline.run(input, ctx);
    ws.set_option(timeouts);  // re-armed by the next read
    const double infer_ms = ms_between(t0, Clock::now());
    if (!answer.ok()) {
      std::string code = "error";
      if (const auto e = answer.body.find("error"); e != answer.body.end() && e->is_object())
        code = e->value("code", code);
      const std::string text = failure_text(answer, ctx.request_id);
      const std::string reason = code + "; reason in the previous frame";
      co_await fail_connection(ws, *conn, text, websocket::close_code::internal_error, reason, opts);
      co_return;
    }
    const std::string reply = openpi::encode_reply(answer.body, {infer_ms, prev_total_ms});
    if (!co_await write_frame(ws, reply, false, opts.write_timeout_ms)) co_return;
    prev_total_ms = ms_between(wait_start, Clock::now());
  }
}

// What the upgrade request gets when it is not upgraded; nullopt: upgrade it.
std::optional<HttpResponse> refusal(Shared& s, const HttpRequest& req, const std::string& key) {
  const ServerOptions& opts = s.opts();
  Metrics& metrics = s.ctx.metrics;
  const std::string_view target = req.target();
  const std::string_view path = target.substr(0, target.find('?'));
  if (path == "/healthz") {  // as openpi's server answers it, before any upgrade
    for (std::size_t i = 0; i < s.ctx.hosts.size(); ++i)
      if (const ModelHost& host = s.ctx.hosts[i]; !host.serving())
        return plain_response(req, http::status::service_unavailable,
                              std::string(health_state_name(host.health())) + "\n", "text/plain", 1);
    return plain_response(req, http::status::ok, "OK\n", "text/plain");
  }
  if (!websocket::is_upgrade(req)) {
    metrics.count_request("upgrade", 426, "openpi");
    return plain_response(req, http::status::upgrade_required,
                          "this port speaks openpi's WebSocket policy protocol (openpi_client.websocket_client_policy);"
                          " GET /healthz for its health\n",
                          "text/plain");
  }
  try {
    check_api_key(key, opts.api_key);
  } catch (const HttpError& e) {
    metrics.count_request("upgrade", e.status(), "openpi");
    return plain_response(req, http::status(e.status()), error_json(e.code(), e.what()), "application/json");
  }
  if (s.draining.load()) {
    metrics.count_request("upgrade", 503, "openpi");
    return plain_response(req, http::status::service_unavailable,
                          error_json("shutting_down", "the server is shutting down"), "application/json", 1);
  }
  // The connection's embodiment: ?embodiment_tag= on the upgrade, else the server's default.
  ModelHost* routed = nullptr;
  try {
    routed = &s.ctx.hosts.route(query_parameter(target, "embodiment_tag"));
  } catch (const HttpError& e) {
    metrics.count_request("upgrade", e.status(), "openpi");
    return plain_response(req, http::status(e.status()), error_json(e.code(), e.what()), "application/json");
  }
  ModelHost& host = *routed;
  if (!host.serving()) {
    metrics.count_request("upgrade", 503, "openpi");
    return plain_response(req, http::status::service_unavailable,
                          error_json("not_ready", std::string("the model is not ready (") +
                                                      health_state_name(host.health()) + ")"),
                          "application/json", 1);
  }
  return std::nullopt;
}

// The refusal of an upgrade request that could not be read; nullopt: just close.
std::optional<HttpResponse> unreadable(Shared& s, const HttpRequest& req, const beast::error_code& ec) {
  if (ec == http::error::header_limit) {
    s.ctx.metrics.count_request("upgrade", 431, "openpi");
    return plain_response(req, http::status::request_header_fields_too_large,
                          error_json("header_too_large", "the request header exceeds " +
                                                             std::to_string(s.opts().max_header_bytes) +
                                                             " bytes (--max-header-bytes)"),
                          "application/json");
  }
  if (ec == http::error::body_limit) {
    s.ctx.metrics.count_request("upgrade", 400, "openpi");
    return plain_response(req, http::status::bad_request,
                          error_json("bad_request", "a WebSocket upgrade request has no body"), "application/json");
  }
  return std::nullopt;
}

net::awaitable<void> session(std::shared_ptr<Shared> s, tcp::socket socket) {
  const ServerOptions& opts = s->opts();
  beast::tcp_stream stream(std::move(socket));
  beast::flat_buffer buffer;
  http::request_parser<http::string_body> parser;
  parser.header_limit(std::uint32_t(std::min<std::size_t>(opts.max_header_bytes, UINT32_MAX)));
  parser.body_limit(kMaxUpgradeBodyBytes);
  beast::error_code ec;
  stream.expires_after(std::chrono::milliseconds(opts.read_timeout_ms));
  co_await http::async_read(stream, buffer, parser, net::redirect_error(net::use_awaitable, ec));
  HttpRequest req = parser.release();
  if (ec) {
    const std::optional<HttpResponse> res = unreadable(*s, req, ec);
    if (res) co_await send_and_close(stream, *res, opts);
    co_return;
  }
  const std::string key = presented_key(req);
  const std::optional<HttpResponse> res = refusal(*s, req, key);
  if (res) {
    co_await send_and_close(stream, *res, opts);
    co_return;
  }
  stream.expires_never();  // the WebSocket's own timeouts apply from here
  auto conn = std::make_shared<OpenpiConnection>(std::move(stream));
  std::string embodiment = query_parameter(req.target(), "embodiment_tag");
  co_await websocket_session(s, conn, std::move(req), key, std::move(embodiment));
}

net::awaitable<void> serve_connection(std::shared_ptr<Shared> s, tcp::socket socket) {
  // Every request failure is answered inside; this keeps a bug in the connection code from ending the process.
  try {
    co_await session(std::move(s), std::move(socket));
  } catch (const std::exception& e) {
    std::fprintf(stderr, "tether serve: openpi connection dropped: %s\n", e.what());
  }
}

net::awaitable<void> accept_loop(std::shared_ptr<Shared> s) {
  for (;;) {
    boost::system::error_code ec;
    // Each connection on its own strand: its stream's timers and I/O completions never run on two threads at once.
    tcp::socket socket =
        co_await s->acceptor.async_accept(net::make_strand(s->ctx.ioc), net::redirect_error(net::use_awaitable, ec));
    if (ec) {
      if (!s->acceptor.is_open()) co_return;
      net::steady_timer pause(s->accept_strand, std::chrono::milliseconds(50));  // e.g. out of descriptors
      co_await pause.async_wait(net::redirect_error(net::use_awaitable, ec));
      continue;
    }
    socket.set_option(tcp::no_delay(true), ec);  // small frames each way: never wait for a delayed ACK
    auto ex = socket.get_executor();
    net::co_spawn(ex, serve_connection(s, std::move(socket)), net::detached);
  }
}

}  // namespace

OpenpiTransport::OpenpiTransport(const TransportContext& ctx)
    : shared_(std::make_shared<Shared>(ctx)) {}

OpenpiTransport::~OpenpiTransport() { stop(); }

uint16_t OpenpiTransport::start() {
  auto& s = *shared_;
  const auto& opts = s.opts();
  const std::string where = opts.host + ":" + std::to_string(*opts.openpi_port);
  boost::system::error_code ec;
  const tcp::endpoint endpoint(net::ip::make_address(resolve_host(opts.host).front()), *opts.openpi_port);
  s.acceptor.open(endpoint.protocol(), ec);
  if (!ec) s.acceptor.set_option(net::socket_base::reuse_address(true), ec);
  if (!ec) s.acceptor.bind(endpoint, ec);
  if (!ec) s.acceptor.listen(net::socket_base::max_listen_connections, ec);
  if (ec) throw Error(ErrorCode::io, "openpi: cannot listen on " + where + " (--openpi-port): " + ec.message());
  const uint16_t port = s.acceptor.local_endpoint().port();
  net::co_spawn(s.accept_strand, accept_loop(shared_), net::detached);
  return port;
}

void OpenpiTransport::begin_draining() {
  auto s = shared_;
  if (s->draining.exchange(true)) return;
  net::post(s->accept_strand, [s] {
    boost::system::error_code ec;
    s->acceptor.close(ec);
  });
  // Connections waiting for a frame are closed now; the others after their reply (websocket_session's loop).
  std::vector<std::shared_ptr<OpenpiConnection>> live;
  {
    std::lock_guard lock(s->mu);
    for (auto& [id, weak] : s->connections)
      if (auto c = weak.lock()) live.push_back(std::move(c));
  }
  for (auto& c : live)
    net::post(c->ws.get_executor(), [c] {
      if (!c->waiting || c->closing) return;
      c->closing = true;
      c->ws.async_close(websocket::close_reason(websocket::close_code::going_away, "server shutting down"),
                        [c](beast::error_code) {});
    });
}

int OpenpiTransport::in_flight() const { return shared_->in_flight.load(); }

void OpenpiTransport::stop() {
  // Called once the io_context has stopped (or never ran): nothing else touches these sockets now.
  auto& s = *shared_;
  boost::system::error_code ec;
  s.acceptor.close(ec);
  std::lock_guard lock(s.mu);
  for (auto& [id, weak] : s.connections)
    if (auto c = weak.lock()) beast::get_lowest_layer(c->ws).socket().close(ec);
}

}  // namespace tether::serve
