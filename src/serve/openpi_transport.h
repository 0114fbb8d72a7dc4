// openpi's WebSocket policy server on its own port (--openpi-port), so openpi_client's WebsocketClientPolicy and
// ActionChunkBroker talk to Tether unchanged: GET /healthz, a metadata frame after the upgrade, then one reply frame
// per observation frame, and on failure a text frame with the reason followed by close code 1011.
#pragma once

#include <memory>

#include "serve/transport.h"

namespace tether::serve {

class OpenpiTransport : public Transport {
 public:
  // Reads --openpi-layout (a mapping file is checked here: throws tether::Error naming it).
  explicit OpenpiTransport(const TransportContext& ctx);
  ~OpenpiTransport() override;

  const char* name() const override { return "openpi"; }
  uint16_t start() override;
  void begin_draining() override;
  int in_flight() const override;
  void stop() override;

  struct Shared;

 private:
  // Shared with every connection's coroutine, which may outlive this object until the io_context is destroyed.
  std::shared_ptr<Shared> shared_;
};

}  // namespace tether::serve
