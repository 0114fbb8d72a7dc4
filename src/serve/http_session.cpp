// The keep-alive loop of one connection: limits while reading, 100-continue, error answers that survive the
// connection closing, and the in-flight count graceful shutdown waits on.
#include "serve/http_session.h"

#include <boost/asio.hpp>
#include <boost/beast.hpp>
#include <chrono>
#include <cstdio>

#include "serve/kserve_endpoints.h"

namespace tether::serve {

namespace net = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
using tcp = net::ip::tcp;

namespace {

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

// After an error response on a request whose body was not read: stop sending, then read and discard what the
// client still sends for a moment, so the response is not lost to a TCP reset.
net::awaitable<void> linger_close(beast::tcp_stream& stream, std::size_t max_discard) {
  beast::error_code ec;
  stream.socket().shutdown(tcp::socket::shutdown_send, ec);
  stream.expires_after(std::chrono::seconds(2));
  std::vector<char> sink(64 * 1024);
  std::size_t discarded = 0;
  while (discarded < max_discard) {
    const std::size_t n =
        co_await stream.async_read_some(net::buffer(sink), net::redirect_error(net::use_awaitable, ec));
    if (ec) break;
    discarded += n;
  }
  stream.socket().close(ec);
}

net::awaitable<void> write_and_close(beast::tcp_stream& stream, HttpResponse res, const ServerOptions& opts) {
  res.keep_alive(false);
  beast::error_code ec;
  stream.expires_after(std::chrono::milliseconds(opts.write_timeout_ms));
  co_await http::async_write(stream, res, net::redirect_error(net::use_awaitable, ec));
  if (!ec) co_await linger_close(stream, opts.max_body_bytes * 4);
}

}  // namespace

HttpSessions::HttpSessions(const ServerOptions& options, Router& router, Metrics& metrics)
    : opts_(options), router_(router), metrics_(metrics) {}

net::awaitable<void> HttpSessions::serve(tcp::socket socket) {
  // Requests already answer every failure; this catch-all keeps a bug in the connection code from ending the process.
  try {
    co_await session(std::move(socket));
  } catch (const std::exception& e) {
    std::fprintf(stderr, "tether serve: connection dropped: %s\n", e.what());
  }
}

net::awaitable<void> HttpSessions::session(tcp::socket socket) {
  beast::tcp_stream stream(std::move(socket));
  beast::flat_buffer buffer;
  // Beast reads as much as the buffer has room for, at least 512 bytes: left at its initial size, a 200 KB /act or
  // KServe body took ~400 reads and 1.2 ms. With 64 KiB of room (Beast's cap per read) it takes a few.
  buffer.reserve(64 * 1024);
  beast::error_code ec;
  for (;;) {
    http::request_parser<http::string_body> parser;
    parser.header_limit(std::uint32_t(std::min<std::size_t>(opts_.max_header_bytes, UINT32_MAX)));
    parser.body_limit(opts_.max_body_bytes);
    stream.expires_after(std::chrono::milliseconds(opts_.read_timeout_ms));
    co_await http::async_read_header(stream, buffer, parser, net::redirect_error(net::use_awaitable, ec));
    const auto received = std::chrono::steady_clock::now();
    InFlight guard(in_flight_, !ec);
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
      HttpRequest partial = parser.get();
      if (partial.version() == 0) partial.version(11);
      const std::string rid = request_id_of(partial);
      if (ec == http::error::body_limit) {
        const std::string why = "the body exceeds " + std::to_string(opts_.max_body_bytes) + " bytes (--max-body-bytes)";
        // A /v2 client gets the protocol's error form, counted under its transport.
        const bool v2 = is_kserve_path(partial.target());
        metrics_.count_request(v2 ? kserve_endpoint_label(partial.target()) : endpoint_label(partial.target()), 413,
                               v2 ? "kserve" : "http");
        // A named local: GCC 12 can destroy temporaries of a co_await operand twice.
        HttpResponse res = v2 ? kserve_error_response(partial, 413, why, rid)
                              : error_response(partial, 413, "body_too_large", why, rid);
        co_await write_and_close(stream, std::move(res), opts_);
      } else if (ec == http::error::header_limit) {
        metrics_.count_request("other", 431);
        co_await write_and_close(stream, error_response(partial, 431, "header_too_large",
                                                "the request header exceeds " +
                                                    std::to_string(opts_.max_header_bytes) +
                                                    " bytes (--max-header-bytes)",
                                                rid),
                                 opts_);
      } else if (&ec.category() == &http::make_error_code(http::error::bad_target).category() &&
                 ec != http::error::end_of_stream && ec != http::error::partial_message) {
        metrics_.count_request("other", 400);
        co_await write_and_close(
            stream, error_response(partial, 400, "bad_request", std::string("malformed HTTP request: ") + ec.message(), rid),
            opts_);
      }
      // Otherwise: the client closed, the connection broke, or a read timed out (the stream is closed then).
      break;
    }
    HttpRequest req = parser.release();
    HttpResponse res = co_await router_.handle(req, received);
    const bool keep = req.keep_alive() && !draining_.load();
    res.keep_alive(keep);
    stream.expires_after(std::chrono::milliseconds(opts_.write_timeout_ms));
    co_await http::async_write(stream, res, net::redirect_error(net::use_awaitable, ec));
    if (ec || !keep) break;
  }
  stream.socket().shutdown(tcp::socket::shutdown_both, ec);
  stream.socket().close(ec);
}

}  // namespace tether::serve
