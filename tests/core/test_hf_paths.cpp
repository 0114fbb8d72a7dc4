// The Hugging Face cache root: one resolution for every caller, in huggingface_hub's precedence.
#include <gtest/gtest.h>

#include <cstdlib>
#include <optional>
#include <string>

#include "core/hf_paths.h"

using namespace tether;

namespace {

// Sets (or unsets) one environment variable for a scope.
class ScopedEnv {
 public:
  ScopedEnv(const char* name, std::optional<std::string> value) : name_(name) {
    if (const char* old = std::getenv(name)) old_ = old;
    if (value) ::setenv(name, value->c_str(), 1);
    else ::unsetenv(name);
  }
  ~ScopedEnv() {
    if (old_) ::setenv(name_, old_->c_str(), 1);
    else ::unsetenv(name_);
  }

 private:
  const char* name_;
  std::optional<std::string> old_;
};

}  // namespace

TEST(HfPaths, HubCachePrecedenceIsHuggingfaceHubs) {
  ScopedEnv home("HOME", "/home/someone");
  ScopedEnv hub("HF_HUB_CACHE", std::nullopt);
  ScopedEnv legacy("HUGGINGFACE_HUB_CACHE", std::nullopt);
  ScopedEnv hf_home_env("HF_HOME", std::nullopt);
  ScopedEnv xdg("XDG_CACHE_HOME", std::nullopt);
  EXPECT_EQ(hf_hub_cache(), "/home/someone/.cache/huggingface/hub");
  EXPECT_EQ(hf_home(), "/home/someone/.cache/huggingface");
  {
    ScopedEnv x("XDG_CACHE_HOME", "/xdg");
    EXPECT_EQ(hf_hub_cache(), "/xdg/huggingface/hub");
    ScopedEnv h("HF_HOME", "/hf");  // HF_HOME beats XDG_CACHE_HOME
    EXPECT_EQ(hf_hub_cache(), "/hf/hub");
    ScopedEnv l("HUGGINGFACE_HUB_CACHE", "/legacy");  // the legacy variable beats HF_HOME
    EXPECT_EQ(hf_hub_cache(), "/legacy");
    ScopedEnv c("HF_HUB_CACHE", "/new");  // and HF_HUB_CACHE beats everything
    EXPECT_EQ(hf_hub_cache(), "/new");
    EXPECT_EQ(hf_home(), "/hf");
  }
  {
    ScopedEnv empty("HF_HUB_CACHE", "");  // set but empty: as if unset
    ScopedEnv l("HUGGINGFACE_HUB_CACHE", "~/legacy");
    EXPECT_EQ(hf_hub_cache(), "/home/someone/legacy");
  }
}

TEST(HfPaths, TildeAndVariablesExpandAsPythonDoes) {
  ScopedEnv home("HOME", "/home/someone");
  ScopedEnv var("TETHER_TEST_DISK", "/mnt/big");
  ScopedEnv unset("TETHER_TEST_UNSET", std::nullopt);
  EXPECT_EQ(expand_user_and_vars("~"), "/home/someone");
  EXPECT_EQ(expand_user_and_vars("~/x"), "/home/someone/x");
  EXPECT_EQ(expand_user_and_vars("~other/x"), "~other/x");  // only the current user's home
  EXPECT_EQ(expand_user_and_vars("$TETHER_TEST_DISK/hf"), "/mnt/big/hf");
  EXPECT_EQ(expand_user_and_vars("${TETHER_TEST_DISK}/hf"), "/mnt/big/hf");
  EXPECT_EQ(expand_user_and_vars("$TETHER_TEST_UNSET/hf"), "$TETHER_TEST_UNSET/hf");  // unknown: left as written
  EXPECT_EQ(expand_user_and_vars("${TETHER_TEST_DISK"), "${TETHER_TEST_DISK");
  ScopedEnv h("HF_HOME", "$TETHER_TEST_DISK/hf");
  ScopedEnv c("HF_HUB_CACHE", std::nullopt);
  ScopedEnv l("HUGGINGFACE_HUB_CACHE", std::nullopt);
  EXPECT_EQ(hf_hub_cache(), "/mnt/big/hf/hub");
}
