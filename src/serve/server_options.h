// Every limit and switch of the action server, with its default; `tether serve` exposes each as a flag.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>

#include "runtime/batcher.h"
#include "runtime/wedges.h"
#include "serve/openpi_options.h"

namespace tether::serve {

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
  std::string model_name;           // KServe v2's model name; empty: the checkpoint directory's (Engine::model_name)

  // Transports beside HTTP (serve/transport.h), on `host`; absent: off, 0: the OS picks a free port.
  std::optional<uint16_t> openpi_port;  // openpi's WebSocket policy server protocol
  OpenpiOptions openpi;                 // its key layout and limits
  std::optional<uint16_t> gr00t_port;   // Isaac-GR00T's ZMQ PolicyClient protocol
  std::optional<uint16_t> zmq_port;     // Tether's own ZMQ protocol (ROUTER: many robots on one port)
  // The ZMQ transports' own limits (docs/transports/gr00t.md, zmq.md): a larger frame makes libzmq drop the peer.
  std::size_t gr00t_max_message_bytes = 64 * 1024 * 1024;
  bool gr00t_allow_kill = false;  // GR00T's "kill" endpoint shuts the server down (else it is refused)
  std::size_t zmq_max_message_bytes = 64 * 1024 * 1024;
  std::string zmq_curve_secret_file;  // Z85 CURVE secret key: the Tether ZMQ port encrypts (empty: plain TCP)
};

}  // namespace tether::serve
