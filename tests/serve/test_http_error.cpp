// HttpError is a tether::Error: its status keeps the stable code string and maps to an ErrorCode; its message is
// text any client can be sent.
#include <gtest/gtest.h>

#include "serve/http_error.h"

using namespace tether;
using namespace tether::serve;

TEST(HttpError, IsATetherErrorThatKeepsItsStatusAndCode) {
  try {
    throw HttpError(503, "circuit_open", "the circuit is open", 7);
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::unavailable);
    EXPECT_STREQ(e.what(), "the circuit is open");
    const auto* http = dynamic_cast<const HttpError*>(&e);
    ASSERT_NE(http, nullptr);
    EXPECT_EQ(http->status(), 503);
    EXPECT_EQ(http->code(), "circuit_open");
    EXPECT_EQ(http->retry_after_s(), 7);
  }
}

TEST(HttpError, StatusesMapToErrorCodes) {
  const std::pair<int, ErrorCode> statuses[] = {
      {400, ErrorCode::invalid_argument}, {401, ErrorCode::unauthenticated}, {404, ErrorCode::not_found},
      {405, ErrorCode::invalid_argument}, {408, ErrorCode::timeout},          {413, ErrorCode::invalid_argument},
      {431, ErrorCode::invalid_argument}, {500, ErrorCode::internal},         {503, ErrorCode::unavailable},
      {504, ErrorCode::timeout}};
  for (const auto& [status, code] : statuses) EXPECT_EQ(error_code_for_status(status), code) << status;
}

TEST(HttpError, MessagesQuotingClientBytesStayWholeAndUtf8) {
  // A msgpack key that starts with a NUL (found by fuzz_openpi_request): what() keeps the whole sentence.
  const HttpError nul(400, "invalid_field", std::string("\0/x: keys must be strings, got integer", 38));
  EXPECT_STREQ(nul.what(), "\\x00/x: keys must be strings, got integer");
  // Control bytes and bytes that are not UTF-8 are escaped; valid UTF-8 is kept.
  EXPECT_EQ(printable_message("a\tb\x1b[31m"), "a\\x09b\\x1b[31m");
  EXPECT_EQ(printable_message("key '\xff\xfe'"), "key '\\xff\\xfe'");
  EXPECT_EQ(printable_message("camera 'k\xc3\xa4mera' \xe7\x9b\xb8"), "camera 'k\xc3\xa4mera' \xe7\x9b\xb8");
  EXPECT_EQ(printable_message("cut \xe7\x9b"), "cut \\xe7\\x9b");  // a sequence the message ends inside
}
