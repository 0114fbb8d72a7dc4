// The API key check shared by every transport.
#include <gtest/gtest.h>

#include "serve/auth.h"
#include "serve/http_error.h"

using namespace tether::serve;

TEST(Auth, KeysCompareExactly) {
  EXPECT_TRUE(keys_equal("abc", "abc"));
  EXPECT_FALSE(keys_equal("abd", "abc"));
  EXPECT_FALSE(keys_equal("ab", "abc"));
  EXPECT_FALSE(keys_equal("abcd", "abc"));
  EXPECT_FALSE(keys_equal("", "abc"));
  EXPECT_FALSE(keys_equal(std::string("abc\0", 4), "abc"));
}

TEST(Auth, CheckApiKey) {
  EXPECT_NO_THROW(check_api_key("", ""));
  EXPECT_NO_THROW(check_api_key("anything", ""));
  EXPECT_NO_THROW(check_api_key("k", "k"));
  for (const auto& [given, says] : {std::pair<std::string, std::string>{"", "is required"}, {"x", "is not valid"}}) {
    try {
      check_api_key(given, "k");
      FAIL() << "accepted '" << given << "'";
    } catch (const HttpError& e) {
      EXPECT_EQ(e.status(), 401);
      EXPECT_EQ(e.code(), "unauthorized");
      EXPECT_NE(std::string(e.what()).find(says), std::string::npos) << e.what();
    }
  }
}
