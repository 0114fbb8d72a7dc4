// --host as addresses to bind: IP addresses as they are, names resolved, an unknown name refused naming it; the ZMQ
// transports' socket bound on a name.
#include <gtest/gtest.h>

#include <boost/asio/io_context.hpp>

#include "core/error.h"
#include "serve/host_address.h"
#include "serve/zmq_server.h"

using namespace tether;
using namespace tether::serve;

TEST(HostAddress, AddressesAreTakenAsTheyAre) {
  EXPECT_EQ(resolve_host("127.0.0.1"), std::vector<std::string>{"127.0.0.1"});
  EXPECT_EQ(resolve_host("0.0.0.0"), std::vector<std::string>{"0.0.0.0"});
}

TEST(HostAddress, NamesAreResolved) {
  const auto addresses = resolve_host("localhost");
  ASSERT_FALSE(addresses.empty());
  for (const auto& a : addresses) EXPECT_TRUE(a == "127.0.0.1" || a == "::1") << a;
}

TEST(HostAddress, AnUnknownNameIsAnInvalidArgumentNamingIt) {
  try {
    resolve_host("no-such-host.invalid");
    FAIL();
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::invalid_argument);
    EXPECT_NE(std::string(e.what()).find("'no-such-host.invalid'"), std::string::npos) << e.what();
  }
}

TEST(HostAddress, ZmqServerBindsAName) {
  boost::asio::io_context ioc;
  const ZmqHandler handler{[](std::string, std::chrono::steady_clock::time_point, ZmqReply) {},
                           [](int, const std::string&, const std::string&) { return std::string(); }};
  ZmqServer on_name({"test", "localhost", 0, 0, std::nullopt}, handler, ioc);
  EXPECT_GT(on_name.start(), 0);
  on_name.stop();
  ZmqServer unknown({"test", "no-such-host.invalid", 0, 0, std::nullopt}, handler, ioc);
  try {
    unknown.start();
    FAIL();
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::invalid_argument);
    EXPECT_NE(std::string(e.what()).find("no-such-host.invalid"), std::string::npos) << e.what();
  }
}
