// HttpError is a tether::Error: its status keeps the stable code string and maps to an ErrorCode.
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
