// The verbs on GR00T checkpoints (the oracle fixtures) through the real binary: N1.7's predict and bench with
// --embodiment-tag, inspect, export and validate of one embodiment, and the embodiment and observation errors (one
// line, exit code 2); N1.6's predict, export and validate, and the error when its Eagle directory is missing.
#include <gtest/gtest.h>

#include <filesystem>
#include <functional>
#include <fstream>

#include "cli_runner.h"
#include "core/json_util.h"
#include "eagle_hub.h"
#include "scratch_dir.h"

namespace fs = std::filesystem;

namespace {

const fs::path kCase = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n17" / "cam2_new";
const fs::path kHub = fs::path(TETHER_FIXTURES_DIR) / "gr00t_hub";

// The binary with a hub cache (default: N1.7's stand-in backbone repository) set for the child only; stderr apart.
CliRun run_gr00t(const std::string& args, const fs::path& hub = kHub) {
  const fs::path err_file = tether::testing::scratch_dir() / "gr00t_cli_err";
  const std::string cmd = "HF_HUB_CACHE=" + hub.string() + " " + TETHER_BINARY + " " + args + " 2>" + err_file.string();
  CliRun r;
  FILE* pipe = popen(cmd.c_str(), "r");
  char buf[4096];
  std::size_t n;
  while ((n = fread(buf, 1, sizeof buf, pipe)) > 0) r.out.append(buf, n);
  const int status = pclose(pipe);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  std::ifstream in(err_file);
  r.err.assign(std::istreambuf_iterator<char>(in), {});
  fs::remove(err_file);
  return r;
}

std::string observation(const std::string& extra = "") {
  return " --image front=" + (kCase / "inputs" / "front.png").string() +
         " --image wrist=" + (kCase / "inputs" / "wrist.png").string() +
         " --state=0.1,0.2,0.3,0.1,0.2,0.3,0.5,0.1,0.2 --instruction 'pick up the cube'" + extra;
}

int lines(const std::string& s) { return int(std::count(s.begin(), s.end(), '\n')); }

TEST(Gr00tCli, PredictAndBenchServeTheChosenEmbodiment) {
  const std::string ckpt = (kCase / "checkpoint").string();
  CliRun r = run_gr00t("predict " + ckpt + observation(" --embodiment-tag new_embodiment --seed 3 --json"));
  ASSERT_EQ(r.code, 0) << r.err;
  const auto j = tether::Json::parse(r.out);
  EXPECT_EQ(j.at("num_actions").get<int>(), 6);  // the checkpoint's action steps, not the model's 8-row horizon
  EXPECT_EQ(j.at("action_dim").get<int>(), 7);
  r = run_gr00t("bench " + ckpt + " --embodiment-tag new_embodiment --iterations 2 --warmup 1 --json");
  ASSERT_EQ(r.code, 0) << r.err;
  r = run_gr00t("inspect model " + ckpt + " --embodiment-tag libero_sim --json");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(tether::Json::parse(r.out).at("family").get<std::string>(), "gr00t_n17");
  EXPECT_EQ(tether::Json::parse(r.out).at("cameras"), tether::Json::array({"image"}));
}

TEST(Gr00tCli, DoctorFitsTheModelAndPointsAtTheEmbodimentTag) {
  const CliRun r = run_gr00t("doctor " + (kCase / "checkpoint").string());
  EXPECT_EQ(r.code, 0) << r.out << r.err;
  EXPECT_NE(r.out.find("gr00t_n17"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("fits in memory (fp32)"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("--embodiment-tag"), std::string::npos) << r.out;
}

// An export of one embodiment holds only its statistics (it loads without naming it), is measured against the
// source and against lerobot's outputs for that embodiment's oracle case, and validates.
TEST(Gr00tCli, ExportOfOneEmbodimentIsVerifiedAndValidates) {
  const fs::path root = tether::testing::scratch_dir() / "gr00t_export";
  fs::remove_all(root);
  struct Case {
    std::string fixture, tag;
  };
  for (const Case& c : {Case{"cam2_new", "new_embodiment"}, Case{"cam1_libero", "libero_sim"}}) {
    const fs::path src = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n17" / c.fixture / "checkpoint";
    const fs::path out = root / c.tag;
    CliRun r = run_gr00t("export " + src.string() + " -o " + out.string() + " --precision bf16 --embodiment-tag " + c.tag);
    ASSERT_EQ(r.code, 0) << r.err;
    const tether::Json manifest = tether::read_json_file((out / "tether_export.json").string());
    EXPECT_EQ(manifest.at("embodiment_tag").get<std::string>(), c.tag);
    bool oracle_row = false;
    for (const auto& d : manifest.at("verification")) {
      EXPECT_LE(d.at("max_abs").get<double>(), 1e-4) << d.dump();
      oracle_row |= d.at("case").get<std::string>() == "oracle-" + c.fixture;
    }
    EXPECT_TRUE(oracle_row) << manifest.dump();
    const tether::Json ids = tether::read_json_file((out / "embodiment_id.json").string());
    EXPECT_EQ(ids.size(), 1u);
    EXPECT_TRUE(ids.contains(c.tag));
    r = run_gr00t("inspect model " + out.string() + " --json");  // no tag needed: the export has one embodiment
    ASSERT_EQ(r.code, 0) << r.err;
    r = run_gr00t("validate export " + out.string() + " --output-json " + (root / (c.tag + ".json")).string());
    EXPECT_EQ(r.code, 0) << r.out << r.err;
    EXPECT_NE(r.out.find("oracle-" + c.fixture), std::string::npos) << r.out;
  }
  // The other embodiment is not in the export; without a tag the multi-embodiment source cannot be exported.
  CliRun r = run_gr00t("predict " + (root / "new_embodiment").string() + observation(" --embodiment-tag libero_sim"));
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("unknown embodiment tag 'libero_sim'"), std::string::npos) << r.err;
  r = run_gr00t("export " + (kCase / "checkpoint").string() + " -o " + (root / "untagged").string());
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("--embodiment-tag"), std::string::npos) << r.err;
  EXPECT_FALSE(fs::exists(root / "untagged"));
  fs::remove_all(root);
}

// Isaac-GR00T's training runs write the sidecars into a `processor/` sub-folder: read from there, and exported there.
TEST(Gr00tCli, SidecarsInAProcessorFolderAreFound) {
  const fs::path ckpt = tether::testing::scratch_dir() / "gr00t_processor_folder";
  fs::remove_all(ckpt);
  fs::create_directories(ckpt / "processor");
  for (const auto& e : fs::directory_iterator(kCase / "checkpoint")) {
    const std::string name = e.path().filename().string();
    const bool sidecar = name == "processor_config.json" || name == "statistics.json" || name == "embodiment_id.json";
    fs::copy_file(e.path(), sidecar ? ckpt / "processor" / name : ckpt / name);
  }
  CliRun r = run_gr00t("predict " + ckpt.string() + observation(" --embodiment-tag new_embodiment --seed 3 --json"));
  ASSERT_EQ(r.code, 0) << r.err;
  const CliRun root = run_gr00t("predict " + (kCase / "checkpoint").string() +
                                observation(" --embodiment-tag new_embodiment --seed 3 --json"));
  ASSERT_EQ(root.code, 0) << root.err;
  EXPECT_EQ(tether::Json::parse(r.out).at("actions"), tether::Json::parse(root.out).at("actions"));
  const fs::path out = tether::testing::scratch_dir() / "gr00t_processor_folder_export";
  fs::remove_all(out);
  r = run_gr00t("export " + ckpt.string() + " -o " + out.string() + " --embodiment-tag new_embodiment");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(fs::exists(out / "processor" / "embodiment_id.json"));
  r = run_gr00t("validate export " + out.string());
  EXPECT_EQ(r.code, 0) << r.out << r.err;
  fs::remove_all(out);
  fs::remove_all(ckpt);
}

TEST(Gr00tCli, EmbodimentAndObservationErrorsAreOneLine) {
  const std::string ckpt = (kCase / "checkpoint").string();
  struct Bad {
    std::string args, says;
  };
  const Bad cases[] = {
      {observation(), "several embodiments; name the one served with --embodiment-tag (libero_sim, new_embodiment)"},
      {observation(" --embodiment-tag robot_x"), "unknown embodiment tag 'robot_x'"},
      {" --image front=" + (kCase / "inputs" / "front.png").string() +
           " --state=0.1,0.2,0.3,0.1,0.2,0.3,0.5,0.1,0.2 --instruction x --embodiment-tag new_embodiment",
       "no image for camera 'wrist'"},
      {" --image front=" + (kCase / "inputs" / "front.png").string() + " --image wrist=" +
           (kCase / "inputs" / "wrist.png").string() + " --state=1,2 --instruction x --embodiment-tag new_embodiment",
       "the model expects 9"},
  };
  for (const Bad& b : cases) {
    const CliRun r = run_gr00t("predict " + ckpt + b.args);
    EXPECT_EQ(r.code, 2) << b.args;
    EXPECT_EQ(lines(r.err), 1) << r.err;
    EXPECT_NE(r.err.find(b.says), std::string::npos) << r.err;
  }
}

TEST(Gr00tCli, ServingSeveralEmbodimentsRefusesAnUnknownOrRepeatedTag) {
  const std::string ckpt = (kCase / "checkpoint").string();
  CliRun r = run_gr00t("serve " + ckpt + " --port 0 --embodiment-tag libero_sim,robot_x");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("error: unknown embodiment tag 'robot_x'"), std::string::npos) << r.err;
  r = run_gr00t("serve " + ckpt + " --port 0 --embodiment-tag libero_sim --embodiment-tag libero_sim");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("error: embodiment 'libero_sim' is named twice"), std::string::npos) << r.err;
  // go exports one embodiment: several are served from the checkpoint.
  r = run_gr00t("go --model gr00t-n1.7 --port 0 --embodiment-tag libero_sim,new_embodiment");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("go serves one --embodiment-tag"), std::string::npos) << r.err;
  // A robot-side file for one embodiment names a served tag, once.
  const std::string two = "serve " + ckpt + " --port 0 --embodiment-tag libero_sim,new_embodiment";
  r = run_gr00t(two + " --embodiment unitree_g1=franka");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("error: --embodiment unitree_g1=franka: 'unitree_g1' is not an embodiment served "
                       "(--embodiment-tag: libero_sim, new_embodiment)"),
            std::string::npos)
      << r.err;
  r = run_gr00t(two + " --embodiment new_embodiment=franka --embodiment new_embodiment=ur5");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("error: --embodiment is given twice for embodiment 'new_embodiment'"), std::string::npos) << r.err;
  r = run_gr00t(two + " --embodiment franka --custom-embodiment-config " + (kCase / "checkpoint" / "config.json").string());
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("error: give --embodiment or --custom-embodiment-config, not both"), std::string::npos) << r.err;
  r = run_gr00t(two + " --openpi-port 0 --openpi-layout robot_x=libero");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("error: --openpi-layout robot_x=libero: 'robot_x' is not an embodiment served"), std::string::npos)
      << r.err;
  r = run_gr00t(two + " --openpi-port 0 --openpi-layout libero_sim=no_such_layout.json");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("--openpi-layout 'no_such_layout.json': neither auto"), std::string::npos) << r.err;
}

// A relative-action checkpoint (tests/fixtures/gr00t_n17_relative) with one sidecar changed: predicts, or fails at
// load with one line naming the group at fault.
TEST(Gr00tCli, RelativeActionConfigsAreReadOrRefusedByName) {
  const fs::path source = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n17_relative";
  const std::string obs = " --image front=" + (source / "inputs" / "front.png").string() + " --image wrist=" +
                          (source / "inputs" / "wrist.png").string() +
                          " --state=0.4,-0.1,0.3,1,0,0,0,1,0,0.2,-0.6,1.1,0.05,0.4 --instruction 'lift the cup' --seed 2";
  struct Change {
    std::string what;  // the JSON file, then how it changes
    std::function<void(tether::Json&)> edit;
    std::string says;  // empty: it predicts
  };
  const Change changes[] = {
      {"processor_config.json", [](tether::Json& j) { j["processor_kwargs"]["use_relative_action"] = false; }, ""},
      {"processor_config.json",
       [](tether::Json& j) {
         j["processor_kwargs"]["modality_configs"]["relative_arm"]["action"]["action_configs"][0]["format"] = "XYZ_ROTVEC";
       },
       "relative action 'eef' is eef xyz+rotvec"},
      {"processor_config.json",
       [](tether::Json& j) {
         j["processor_kwargs"]["modality_configs"]["relative_arm"]["action"]["action_configs"][1]["state_key"] = "base";
       },
       "relative action 'joints' names state 'base', which the embodiment does not have"},
      {"statistics.json",
       [](tether::Json& j) {
         auto& lo = j["relative_arm"]["relative_action"]["eef"]["min"];
         lo.erase(lo.begin() + 3, lo.end());
       },
       "relative_action 'eef' min has 3 steps for a chunk of 6"},
      {"statistics.json", [](tether::Json& j) { j["relative_arm"]["relative_action"].erase("joints"); },
       "no relative_action statistics for 'joints'"},
  };
  for (const Change& c : changes) {
    const fs::path dir = tether::testing::scratch_dir() / "gr00t_relative_edit";
    fs::remove_all(dir);
    fs::create_directories(dir);
    for (const auto& f : fs::directory_iterator(source / "checkpoint")) {
      if (f.path().filename() == c.what) continue;
      fs::create_symlink(f.path(), dir / f.path().filename());
    }
    tether::Json j = tether::read_json_file((source / "checkpoint" / c.what).string());
    c.edit(j);
    std::ofstream(dir / c.what) << j.dump(1);
    const CliRun r = run_gr00t("predict " + dir.string() + obs);
    if (c.says.empty()) {
      EXPECT_EQ(r.code, 0) << r.err;
    } else {
      EXPECT_EQ(r.code, 2) << c.says;
      EXPECT_EQ(lines(r.err), 1) << r.err;
      EXPECT_NE(r.err.find(c.says), std::string::npos) << r.err;
    }
  }
}

// N1.6: the checkpoint names Isaac-GR00T's Eagle directory, put in a hub cache under that id (eagle_hub.h).
const fs::path kN16 = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n16";

TEST(Gr00tN16Cli, PredictExportAndValidateOneEmbodiment) {
  const fs::path hub = tether::testing::eagle_hub_cache(), ckpt = kN16 / "checkpoint";
  const fs::path img = kN16 / "cases" / "cam1_libero_panda" / "inputs" / "image.png";
  // libero_panda's raw state: eef_pos 3, eef_rot 3 (sin/cos encoded), gripper 2 (mean/std).
  const std::string obs = " --image image=" + img.string() + " --state=0.1,0.2,0.3,0.4,0.5,0.6,0.01,0.02 --instruction 'put the bowl on the plate'";
  CliRun r = run_gr00t("predict " + ckpt.string() + obs + " --embodiment-tag libero_panda --seed 1 --json", hub);
  ASSERT_EQ(r.code, 0) << r.err;
  const auto j = tether::Json::parse(r.out);
  EXPECT_EQ(j.at("num_actions").get<int>(), 6);
  EXPECT_EQ(j.at("action_dim").get<int>(), 7);
  r = run_gr00t("inspect model " + ckpt.string() + " --embodiment-tag new_embodiment --json", hub);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(tether::Json::parse(r.out).at("family").get<std::string>(), "gr00t_n16");
  const fs::path out = tether::testing::scratch_dir() / "gr00t_n16_export";
  fs::remove_all(out);
  r = run_gr00t("export " + ckpt.string() + " -o " + out.string() + " --precision bf16 --embodiment-tag libero_panda", hub);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(fs::exists(out / "nvidia" / "Eagle-Block2A-2B-v2" / "tokenizer.json"));  // the export carries Eagle
  // The export loads without the hub cache (its Eagle copy) and without a tag (one embodiment), and validates.
  r = run_gr00t("validate export " + out.string(), hub);
  EXPECT_EQ(r.code, 0) << r.out << r.err;
  r = run_gr00t("predict " + out.string() + obs + " --seed 1 --json", tether::testing::scratch_dir() / "no_hub");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(tether::Json::parse(r.out).at("actions"), j.at("actions"));  // bf16 of bf16 weights: the same numbers
  fs::remove_all(out);
}

// An N1.6 embodiment with relative actions (tests/fixtures/gr00t_n16_decode) serves through every verb: predict
// re-anchors against the request's state, export at bf16 validates. A relative group also listed for mean/std is
// refused by name, in one line, exit code 2.
TEST(Gr00tN16Cli, RelativeActionsPredictExportAndValidate) {
  const fs::path hub = tether::testing::eagle_hub_cache(), root = kN16.parent_path() / "gr00t_n16_decode";
  const fs::path ckpt = root / "checkpoint", inputs = root / "cases" / "relative_arm" / "inputs";
  const std::string obs = " --image front=" + (inputs / "front.png").string() + " --image wrist=" +
                          (inputs / "wrist.png").string() +
                          " --instruction 'lift the cup' --embodiment-tag relative_arm --seed 1 --json";
  // eef: xyz + an identity rotation's rows; joints; gripper. Moving the state moves the relative groups only.
  const std::string at_origin = " --state=0,0,0,1,0,0,0,1,0,0,0,0,0,0.4",
                    moved = " --state=1,0,0,1,0,0,0,1,0,2,0,0,0,0.4";
  CliRun a = run_gr00t("predict " + ckpt.string() + at_origin + obs, hub);
  ASSERT_EQ(a.code, 0) << a.err;
  CliRun b = run_gr00t("predict " + ckpt.string() + moved + obs, hub);
  ASSERT_EQ(b.code, 0) << b.err;
  const auto ja = tether::Json::parse(a.out), jb = tether::Json::parse(b.out);
  ASSERT_EQ(ja.at("action_dim").get<int>(), 14);
  const auto& ra = ja.at("actions");
  const auto& rb = jb.at("actions");
  // The state enters the model too, so only the shift's direction is checked: eef x and joints[0] follow the state.
  EXPECT_GT(rb.at(0).at(0).get<double>() - ra.at(0).at(0).get<double>(), 0.5);
  EXPECT_GT(rb.at(0).at(9).get<double>() - ra.at(0).at(9).get<double>(), 1.0);

  const fs::path out = tether::testing::scratch_dir() / "gr00t_n16_relative_export";
  fs::remove_all(out);
  CliRun r =
      run_gr00t("export " + ckpt.string() + " -o " + out.string() + " --precision bf16 --embodiment-tag relative_arm", hub);
  ASSERT_EQ(r.code, 0) << r.err;
  r = run_gr00t("validate export " + out.string(), hub);
  EXPECT_EQ(r.code, 0) << r.out << r.err;
  fs::remove_all(out);

  const fs::path bad = tether::testing::scratch_dir() / "gr00t_n16_mean_std_action";
  fs::remove_all(bad);
  fs::copy(ckpt, bad, fs::copy_options::recursive);
  tether::Json pc = tether::read_json_file((bad / "processor_config.json").string());
  pc["processor_kwargs"]["modality_configs"]["relative_arm"]["action"]["mean_std_embedding_keys"] = {"joints"};
  std::ofstream(bad / "processor_config.json") << pc.dump(2);
  r = run_gr00t("predict " + bad.string() + at_origin + obs, hub);
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find("action 'joints' is both relative and decoded with mean/std"), std::string::npos) << r.err;

  // Without use_percentiles, N1.6 decodes with min/max (Isaac-GR00T's default), as the fixture's explicit false does.
  pc["processor_kwargs"]["modality_configs"]["relative_arm"]["action"].erase("mean_std_embedding_keys");
  pc["processor_kwargs"].erase("use_percentiles");
  std::ofstream(bad / "processor_config.json") << pc.dump(2);
  r = run_gr00t("predict " + bad.string() + at_origin + obs, hub);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(tether::Json::parse(r.out).at("actions"), ra);
  fs::remove_all(bad);
}

TEST(Gr00tN16Cli, MissingEagleDirectorySaysWhereItComesFrom) {
  const CliRun r = run_gr00t("predict " + (kN16 / "checkpoint").string() + " --embodiment-tag libero_panda --image image=" +
                               (kN16 / "cases" / "cam1_libero_panda" / "inputs" / "image.png").string() +
                               " --state=0,0,0,0,0,0,0,0 --instruction x",
                           tether::testing::scratch_dir() / "no_hub");
  EXPECT_EQ(r.code, 2);
  EXPECT_EQ(lines(r.err), 1) << r.err;
  EXPECT_NE(r.err.find("gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2"), std::string::npos) << r.err;
}

}  // namespace
