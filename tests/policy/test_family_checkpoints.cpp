// Checkpoints through the family contract end to end: a sharded copy of a fixture predicts the same bits, a
// pre-0.4 checkpoint loads with its statistics and says so.
#include <gtest/gtest.h>

#include <unistd.h>

#include <filesystem>
#include <fstream>

#include "core/safetensors.h"
#include "policy/policy.h"
#include "scratch_dir.h"

using namespace tether;
namespace fs = std::filesystem;

namespace {

const fs::path kFixtures = fs::path(TETHER_FIXTURES_DIR) / "smolvla";

std::vector<float> predict(policy::Policy& p, const fs::path& case_dir) {
  policy::Observation o;
  o.images[p.spec().cameras.at(0)] = vision::load_image((case_dir / "inputs" / "camera1_0.png").string());
  o.state.assign(std::size_t(p.spec().state_dim), 0.5f);
  o.instruction = "pick up the red cube";
  o.seed = 3;
  return p.predict({o}).items.at(0).actions;
}

}  // namespace

TEST(FamilyCheckpoints, ShardedWeightsPredictTheSameBits) {
  const fs::path src = kFixtures / "cam1_stats" / "checkpoint";
  const fs::path dst = tether::testing::scratch_dir() / "sharded";
  fs::remove_all(dst);
  fs::copy(src, dst, fs::copy_options::recursive);
  fs::remove(dst / "model.safetensors");
  // Three shards, tensors dealt round-robin, as an index maps them.
  const SafeTensorsFile whole = SafeTensorsFile::open((src / "model.safetensors").string());
  std::map<std::string, Tensor> shards[3];
  Json map = Json::object();
  int i = 0;
  for (const auto& name : whole.names()) {
    const int s = i++ % 3;
    shards[s][name] = whole.get(name);
    map[name] = "model-0000" + std::to_string(s + 1) + "-of-00003.safetensors";
  }
  for (int s = 0; s < 3; ++s)
    write_safetensors((dst / ("model-0000" + std::to_string(s + 1) + "-of-00003.safetensors")).string(), shards[s]);
  std::ofstream(dst / "model.safetensors.index.json") << Json{{"metadata", {{"total_size", 0}}}, {"weight_map", map}}.dump();

  auto single = policy::Policy::load(src.string());
  auto sharded = policy::Policy::load(dst.string());
  EXPECT_EQ(single->weight_files(), std::vector<std::string>{"model.safetensors"});
  EXPECT_EQ(sharded->weight_files().size(), 4u);  // the index and three shards
  EXPECT_EQ(sharded->weight_files().front(), "model.safetensors.index.json");
  EXPECT_EQ(predict(*single, kFixtures / "cam1_stats"), predict(*sharded, kFixtures / "cam1_stats"));
  EXPECT_NE(models::weights_hash(src, single->weight_files()), models::weights_hash(dst, sharded->weight_files()));
  fs::remove_all(dst);
}

TEST(FamilyCheckpoints, LegacyLayoutLoadsWithItsStatisticsAndANotice) {
  const fs::path dir = kFixtures / "legacy_pre04" / "checkpoint";
  ASSERT_FALSE(fs::exists(dir / "policy_preprocessor.json"));
  auto p = policy::Policy::load(dir.string());
  ASSERT_FALSE(p->load_warnings().empty());
  EXPECT_NE(p->load_warnings()[0].find("legacy checkpoint"), std::string::npos) << p->load_warnings()[0];
  EXPECT_EQ(p->load_warnings().size(), 1u) << "every normalised feature has its statistics";
  const auto& state = p->input_normalizer().features().at("observation.state");
  EXPECT_EQ(state.mode, policy::NormMode::min_max);
  EXPECT_TRUE(state.has_stats);
  const auto& action = p->output_normalizer().features().at("action");
  EXPECT_EQ(action.mode, policy::NormMode::mean_std);
  EXPECT_TRUE(action.has_stats);
  EXPECT_EQ(p->family().name, "smolvla");
}
