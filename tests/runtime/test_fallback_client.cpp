// The fallback client without a network: the request it sends and how it judges each kind of reply.
#include <gtest/gtest.h>

#include <algorithm>

#include "runtime/fallback_client.h"

using namespace tether;
using namespace tether::runtime;

namespace {

hub::HttpResult reply(long status, std::string body) {
  hub::HttpResult r;
  r.response.status = status;
  r.response.body = std::move(body);
  return r;
}

bool has(const std::vector<std::string>& v, const std::string& s) { return std::find(v.begin(), v.end(), s) != v.end(); }

}  // namespace

TEST(FallbackClient, RequestGoesToActWithTheIdTheMarkerAndTheKey) {
  const FallbackClient client("http://cloud:8000/", 1500, "k3y");
  const hub::HttpRequest r = client.request_for("{\"state\":[1]}", "req-7");
  EXPECT_EQ(r.method, "POST");
  EXPECT_EQ(r.url, "http://cloud:8000/act");
  EXPECT_EQ(r.body, "{\"state\":[1]}");
  EXPECT_EQ(r.timeout_ms, 1500);
  EXPECT_TRUE(has(r.headers, "X-Tether-Request-ID: req-7"));
  EXPECT_TRUE(has(r.headers, "X-Tether-Fallback: 1"));
  EXPECT_TRUE(has(r.headers, "Authorization: Bearer k3y"));
  EXPECT_TRUE(has(r.headers, "Content-Type: application/json"));
  const hub::HttpRequest open = FallbackClient("http://cloud:8000", 1500, "").request_for("{}", "r");
  EXPECT_EQ(open.url, "http://cloud:8000/act");
  for (const auto& h : open.headers) EXPECT_EQ(h.rfind("Authorization", 0), std::string::npos) << h;
}

TEST(FallbackClient, AcceptsRowsOfTheActionDimension) {
  const FallbackReply r = FallbackClient::read_reply(reply(200, R"({"actions": [[1, 2], [3.5, -4]]})"), 2);
  ASSERT_TRUE(r.actions.has_value()) << r.error;
  EXPECT_EQ(r.rows, 2);
  EXPECT_EQ(*r.actions, (std::vector<float>{1, 2, 3.5f, -4}));
  EXPECT_TRUE(r.error.empty());
}

TEST(FallbackClient, SaysWhyAReplyIsRefused) {
  hub::HttpResult unreachable;
  unreachable.failure = hub::TransportFailure::connect;
  unreachable.error = "Could not connect";
  const std::pair<hub::HttpResult, std::string> cases[] = {
      {unreachable, "fallback unreachable: Could not connect"},
      {reply(503, "{}"), "fallback answered HTTP 503"},
      {reply(200, "not json"), "fallback answered without an actions array"},
      {reply(200, R"({"actions": []})"), "fallback answered without an actions array"},
      {reply(200, R"({"actions": [[1, 2, 3]]})"), "fallback actions do not have 2 values per row"},
      {reply(200, R"({"actions": [[1, "x"]]})"), "fallback actions hold a non-number"}};
  for (const auto& [result, why] : cases) {
    const FallbackReply r = FallbackClient::read_reply(result, 2);
    EXPECT_FALSE(r.actions.has_value()) << why;
    EXPECT_EQ(r.error, why);
  }
}
