// `tether inspect targets` and `tether inspect model`.
#include <gtest/gtest.h>

#include "cli_runner.h"
#include "core/json_util.h"

using namespace tether;

TEST(InspectCli, TargetsListTheProfiles) {
  const CliRun r = run_tether("inspect targets --json");
  ASSERT_EQ(r.code, 0) << r.err;
  std::vector<std::string> ids;
  for (const auto& t : Json::parse(r.out)) {
    ids.push_back(t["id"]);
    EXPECT_GT(t["memory_gb"].get<int>(), 0);
    EXPECT_FALSE(t["default_precision"].get<std::string>().empty());
  }
  EXPECT_EQ(ids, (std::vector<std::string>{"orin-nano", "orin", "orin-64", "thor", "desktop"}));
}

TEST(InspectCli, ModelSummary) {
  const CliRun r = run_tether("inspect model " + std::string(TETHER_SOURCE_DIR) + "/models/demo/smolvla-demo --json");
  ASSERT_EQ(r.code, 0) << r.err;
  const Json j = Json::parse(r.out);
  EXPECT_EQ(j["family"], "smolvla");
  EXPECT_EQ(j["cameras"][0], "observation.images.front");
  EXPECT_EQ(j["action_dim"], 6);
  EXPECT_GT(j["parameters"].get<int64_t>(), 100000);
  EXPECT_EQ(run_tether("inspect model /nonexistent").code, 2);
  EXPECT_EQ(run_tether("inspect").code, 2);
}
