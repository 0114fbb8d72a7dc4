// The verbs on pi0 and pi0.5 checkpoints (the oracle fixtures) through the real binary: predict, bench, inspect,
// doctor, export at every precision with validate, an export that runs with an empty hub cache, and bad input
// (config, request, weights, tokenizer) failing with one line and exit code 2.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <functional>

#include "cli_runner.h"
#include "core/json_util.h"
#include "core/safetensors.h"
#include "scratch_dir.h"

using namespace tether;
namespace fs = std::filesystem;

namespace {

const fs::path kFixtures = TETHER_FIXTURES_DIR;
const fs::path kHub = kFixtures / "paligemma_hub";
const std::string kTokenizerRepo = "google/paligemma-3b-pt-224";
const fs::path kHubSnapshot =
    kHub / "models--google--paligemma-3b-pt-224" / "snapshots" / "7f1a0c1b5e0d4a2c9b3e8f6d5c4b3a2918070605";

// One fixture case and the observation flags that fit it.
struct Case {
  std::string family, name, camera, image, state;
  fs::path checkpoint() const { return kFixtures / family / name / "checkpoint"; }
  std::string observation(const std::string& instruction = "pick up the cube") const {
    return " --image " + camera + "=" + (kFixtures / family / name / "inputs" / image).string() + " --state " + state +
           " --instruction '" + instruction + "'";
  }
};
const Case kPi0{"pi0", "cam1_stats", "camera1", "camera1_0.png", "0.5,-1,2,0,1,3"};
const Case kPi05{"pi05", "cam1_quantiles_bins", "camera1", "camera1_0.png", "0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8"};

int lines(const std::string& s) { return int(std::count(s.begin(), s.end(), '\n')); }

std::string read(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), {}};
}

// A scratch directory per test, removed afterwards.
struct Scratch {
  fs::path path;
  explicit Scratch(const std::string& name)
      : path(tether::testing::scratch_dir() / ("pi0_cli_" + name)) {
    fs::remove_all(path);
    fs::create_directories(path);
  }
  ~Scratch() { fs::remove_all(path); }
  fs::path operator/(const std::string& p) const { return path / p; }
};

// The binary run under `prefix` (environment assignments, a wrapper such as `timeout 60`), stderr apart.
CliRun run_prefixed(const std::string& prefix, const std::string& args) {
  const fs::path err_file = tether::testing::scratch_dir() / "pi0_cli_err";
  CliRun r;
  FILE* pipe = popen((prefix + " " + TETHER_BINARY + " " + args + " 2>" + err_file.string()).c_str(), "r");
  char buf[4096];
  std::size_t n;
  while ((n = fread(buf, 1, sizeof buf, pipe)) > 0) r.out.append(buf, n);
  const int status = pclose(pipe);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  r.err = read(err_file);
  fs::remove(err_file);
  return r;
}

// The binary with HF_HUB_CACHE set for the child only.
CliRun run_with_hub(const fs::path& hub, const std::string& args) {
  return run_prefixed("HF_HUB_CACHE=" + hub.string(), args);
}

// An instruction whose bytes are given as printf escapes (the shell popen runs has no $'...').
std::string raw_instruction(const std::string& printf_escapes) {
  return " --instruction \"$(printf '" + printf_escapes + "')\"";
}

// A copy of `src` whose model.safetensors has tensor `name` stored with `shape` (same number of elements, so only the
// header disagrees with the model).
void copy_with_shape(const fs::path& src, const fs::path& dst, const std::string& name, const Shape& shape) {
  fs::copy(src, dst, fs::copy_options::recursive);
  std::map<std::string, Tensor> tensors;
  {
    const SafeTensorsFile f = SafeTensorsFile::open((src / "model.safetensors").string());
    for (const auto& n : f.names()) {
      Tensor t = f.get(n);
      std::vector<float> v = t.to_f32();
      tensors[n] = Tensor::from_f32(n == name ? shape : t.shape, v);
    }
    ASSERT_TRUE(tensors.count(name)) << name;
    ASSERT_EQ(shape_numel(shape), shape_numel(f.entry(name).shape)) << name;
  }
  write_safetensors((dst / "model.safetensors").string(), tensors);
}

void edit_config(const fs::path& dir, const std::function<void(Json&)>& edit) {
  Json c = read_json_file((dir / "config.json").string());
  edit(c);
  std::ofstream(dir / "config.json", std::ios::trunc) << c.dump(4);
}

class Pi0Cli : public ::testing::Test {
 protected:
  void SetUp() override { ::setenv("HF_HUB_CACHE", kHub.c_str(), 1); }
  void TearDown() override { ::unsetenv("HF_HUB_CACHE"); }
};

}  // namespace

TEST_F(Pi0Cli, PredictPrintsTheChunkAndTheFamilysStages) {
  for (const Case& c : {kPi0, kPi05}) {
    const CliRun r = run_tether("predict " + c.checkpoint().string() + c.observation() + " --seed 3 --json");
    ASSERT_EQ(r.code, 0) << c.family << ": " << r.err;
    const Json j = Json::parse(r.out);
    EXPECT_EQ(j["model"]["family"], c.family);
    EXPECT_EQ(j["num_actions"], 8) << c.family;
    EXPECT_EQ(j["action_dim"], 6) << c.family;
    ASSERT_EQ(j["actions"].size(), 8u);
    EXPECT_EQ(j["actions"][0].size(), 6u);
    for (const char* stage : {"load", "normalize", "preprocess", "vision", "prefix", "denoise", "postprocess", "total"})
      EXPECT_TRUE(j["latency_ms"].contains(stage)) << c.family << " " << stage;
    EXPECT_TRUE(j["warnings"].empty()) << j["warnings"];
    // Same seed, same chunk; another instruction, another chunk (the prompt reaches the model).
    EXPECT_EQ(Json::parse(run_tether("predict " + c.checkpoint().string() + c.observation() + " --seed 3 --json").out)["actions"],
              j["actions"]);
    EXPECT_NE(Json::parse(run_tether("predict " + c.checkpoint().string() + c.observation("open the drawer") +
                                     " --seed 3 --json").out)["actions"],
              j["actions"]);
    const CliRun table = run_tether("predict " + c.checkpoint().string() + c.observation() + " --seed 3");
    ASSERT_EQ(table.code, 0) << table.err;
    EXPECT_NE(table.out.find("action chunk: 8 x 6 (robot units)"), std::string::npos) << table.out;
    EXPECT_NE(table.out.find(" vision "), std::string::npos) << table.out;
  }
}

TEST_F(Pi0Cli, PredictAnnouncesAMissingCamera) {
  // cam3_missing_empty: three cameras and an empty one; camera2 left out is masked, as upstream does.
  const fs::path dir = kFixtures / "pi0" / "cam3_missing_empty";
  const CliRun r = run_tether("predict " + (dir / "checkpoint").string() + " --image camera1=" +
                              (dir / "inputs" / "camera1_0.png").string() + " --image camera3=" +
                              (dir / "inputs" / "camera3_0.png").string() + " --state 0,0,0,0,0,0,0 --instruction go --json");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("warning: no image for camera 'observation.images.camera2': masked out"), std::string::npos)
      << r.err;
  EXPECT_EQ(r.err.find("empty_camera_0"), std::string::npos) << "the model's own placeholder is not a warning: " << r.err;
  EXPECT_EQ(Json::parse(r.out)["warnings"].size(), 1u);
}

TEST_F(Pi0Cli, BenchReportsTheFamilyAndItsStages) {
  for (const Case& c : {kPi0, kPi05}) {
    const CliRun r = run_tether("bench " + c.checkpoint().string() + c.observation() +
                                " --iterations 3 --warmup 1 --batch 2 --json");
    ASSERT_EQ(r.code, 0) << c.family << ": " << r.err;
    const Json j = Json::parse(r.out);
    EXPECT_EQ(j["family"], c.family);
    EXPECT_EQ(j["batch"], 2);
    EXPECT_EQ(j["iterations"], 3);
    for (const char* stage : {"preprocess", "vision", "prefix", "denoise"})
      EXPECT_TRUE(j["stages_ms"].contains(stage)) << c.family << " " << stage;
    EXPECT_GT(j["latency_ms"]["mean"].get<double>(), 0.0);
    EXPECT_GT(j["gflop_per_chunk"].get<double>(), 0.0);
    // With synthetic inputs (no flags) and adaptive steps measured against all steps.
    const CliRun adaptive =
        run_tether("bench " + c.checkpoint().string() + " --iterations 2 --warmup 0 --adaptive-threshold 0.5");
    ASSERT_EQ(adaptive.code, 0) << adaptive.err;
    EXPECT_NE(adaptive.out.find("(" + c.family + ", cpu-fp32, batch 1"), std::string::npos) << adaptive.out;
    EXPECT_NE(adaptive.out.find("adaptive     threshold 0.5: steps used"), std::string::npos) << adaptive.out;
  }
}

TEST_F(Pi0Cli, InspectShowsFamilyCamerasStagesAndWhereTheTokenizerCameFrom) {
  for (const Case& c : {kPi0, kPi05}) {
    const CliRun r = run_tether("inspect model " + c.checkpoint().string() + " --json");
    ASSERT_EQ(r.code, 0) << r.err;
    const Json j = Json::parse(r.out);
    EXPECT_EQ(j["family"], c.family);
    EXPECT_EQ(j["cameras"], Json::array({"observation.images.camera1"}));
    EXPECT_EQ(j["stages"], Json::array({"preprocess", "vision", "prefix", "denoise"}));
    EXPECT_EQ(j["tokenizer"], "sentencepiece");
    EXPECT_EQ(j["tokenizer_source"], (kHubSnapshot / "tokenizer.json").string());
    EXPECT_EQ(j["image_size"], Json::array({56, 56}));
    EXPECT_EQ(j["chunk_size"], 8);
    EXPECT_EQ(j["weights_dtype"], "F32");
  }
  // Three cameras and the config's empty camera, in model order; bf16 weights.
  const CliRun multi = run_tether("inspect model " + (kFixtures / "pi05" / "cam3_missing_empty" / "checkpoint").string() + " --json");
  ASSERT_EQ(multi.code, 0) << multi.err;
  EXPECT_EQ(Json::parse(multi.out)["cameras"],
            Json::array({"observation.images.camera1", "observation.images.camera2", "observation.images.camera3",
                         "observation.images.empty_camera_0"}));
  const CliRun bf16 = run_tether("inspect model " + (kFixtures / "pi0" / "cam2_bf16" / "checkpoint").string());
  ASSERT_EQ(bf16.code, 0) << bf16.err;
  EXPECT_NE(bf16.out.find("family               \"pi0\""), std::string::npos) << bf16.out;
  EXPECT_NE(bf16.out.find("weights_dtype        \"BF16\""), std::string::npos) << bf16.out;
}

TEST_F(Pi0Cli, DoctorReportsTheFamilyAndBothMemoryFits) {
  for (const Case& c : {kPi0, kPi05}) {
    const CliRun r = run_tether("doctor " + c.checkpoint().string() + " --json");
    const Json j = Json::parse(r.out);
    std::map<std::string, Json> model;
    for (const auto& check : j["checks"])
      if (check["group"] == "model") model[check["check"].get<std::string>()] = check;
    ASSERT_TRUE(model.count("family")) << r.out;
    EXPECT_EQ(model["family"]["status"], "ok");
    EXPECT_EQ(model["family"]["detail"].get<std::string>().rfind(c.family + " (config.json \"type\": \"" + c.family + "\"", 0), 0u)
        << model["family"];
    for (const char* fit : {"fits in memory (fp32)", "fits in memory (bf16)"}) {
      ASSERT_TRUE(model.count(fit)) << fit << "\n" << r.out;
      EXPECT_EQ(model[fit]["status"], "ok") << model[fit];
      EXPECT_NE(model[fit]["detail"].get<std::string>().find("needs about "), std::string::npos) << model[fit];
    }
    EXPECT_EQ(model["normalisation"]["status"], "ok") << model["normalisation"];
    EXPECT_EQ(model["weights"]["status"], "ok") << model["weights"];
    const CliRun table = run_tether("doctor " + c.checkpoint().string());
    EXPECT_NE(table.out.find("fits in memory (fp32)"), std::string::npos) << table.out;
    EXPECT_NE(table.out.find("fits in memory (bf16)"), std::string::npos) << table.out;
  }
  // No stats: a warning naming the features, not a failure.
  const CliRun nostats = run_tether("doctor " + (kFixtures / "pi0" / "cam3_nostats_trunc" / "checkpoint").string() + " --json");
  for (const auto& check : Json::parse(nostats.out)["checks"])
    if (check["check"] == "normalisation") {
      EXPECT_EQ(check["status"], "warn") << check;
    }
}

TEST_F(Pi0Cli, ExportAtEveryPrecisionValidatesAndRunsWithAnEmptyHubCache) {
  Scratch tmp("export");
  const fs::path empty_hub = tmp / "empty_hub";
  fs::create_directories(empty_hub);
  for (const Case& c : {kPi0, kPi05}) {
    const CliRun source = run_tether("predict " + c.checkpoint().string() + c.observation() + " --seed 5 --json");
    ASSERT_EQ(source.code, 0) << source.err;
    for (const std::string precision : {"fp32", "bf16", "fp16"}) {
      const std::string label = c.family + " " + precision;
      const fs::path out = tmp / (c.family + "-" + precision);
      const CliRun e = run_tether("export " + c.checkpoint().string() + " -o " + out.string() + " --precision " + precision);
      ASSERT_EQ(e.code, 0) << label << ": " << e.err;
      // The tokenizer travels with the export, under the repo id the preprocessor names.
      for (const char* f : {"tokenizer.json", "tokenizer.model", "tokenizer_config.json", "config.json"})
        EXPECT_EQ(read(out / kTokenizerRepo / f), read(kHubSnapshot / f)) << label << " " << f;
      const std::string receipt = read(out / "VERIFICATION.md");
      for (const std::string& part : std::vector<std::string>{"precision **" + precision + "**", "| " + kTokenizerRepo + "/tokenizer.json |",
                                     "into `" + kTokenizerRepo + "/`", "seeded-3", "oracle-" + c.name})
        EXPECT_NE(receipt.find(part), std::string::npos) << label << ": " << part;
      const Json manifest = read_json_file((out / "tether_export.json").string());
      EXPECT_EQ(manifest["precision"], precision);
      EXPECT_TRUE(manifest["files"].contains(kTokenizerRepo + "/tokenizer.model")) << label;
      const DType stored = SafeTensorsFile::open((out / "model.safetensors").string()).entry("model.action_in_proj.weight").dtype;
      EXPECT_EQ(stored, precision == "fp32" ? DType::f32 : precision == "bf16" ? DType::bf16 : DType::f16) << label;

      // validate: the files, then the actions against the source (fp32 within 1e-4; half precision is measured, and
      // passes only a looser threshold).
      const CliRun v = run_tether("validate export " + out.string() + " --output-json " + (out / "v.json").string() +
                                  (precision == "fp32" ? "" : " --threshold 2"));
      EXPECT_EQ(v.code, 0) << label << ": " << v.out << v.err;
      const Json vj = read_json_file((out / "v.json").string());
      EXPECT_TRUE(vj["pass"].get<bool>()) << vj;
      EXPECT_EQ(vj["checks"].size(), 6u) << vj;  // files, 4 seeded, the oracle
      if (precision != "fp32") {
        EXPECT_EQ(run_tether("validate export " + out.string()).code, 1) << label;
      }

      // Self-contained: with nothing in the hub cache the export loads and predicts (the source no longer does).
      const CliRun alone = run_with_hub(empty_hub, "predict " + out.string() + c.observation() + " --seed 5 --json");
      ASSERT_EQ(alone.code, 0) << label << ": " << alone.err;
      if (precision == "fp32") {
        EXPECT_EQ(Json::parse(alone.out)["actions"], Json::parse(source.out)["actions"]) << label;
      }
      const CliRun inspect = run_with_hub(empty_hub, "inspect model " + out.string() + " --json");
      ASSERT_EQ(inspect.code, 0) << inspect.err;
      EXPECT_EQ(Json::parse(inspect.out)["tokenizer_source"], (out / kTokenizerRepo / "tokenizer.json").string());
    }
    const CliRun without = run_with_hub(empty_hub, "predict " + c.checkpoint().string() + c.observation());
    EXPECT_EQ(without.code, 2) << without.err;
    // validate needs the reference too, and says that it is the reference that did not load.
    const CliRun v = run_with_hub(empty_hub, "validate export " + (tmp / (c.family + "-fp32")).string());
    EXPECT_EQ(v.code, 1) << v.out;
    EXPECT_NE(v.out.find("load the reference: '" + kTokenizerRepo + "'"), std::string::npos) << v.out;
  }
}

TEST_F(Pi0Cli, EveryFixtureExportsAndValidates) {
  // Every case, fp32: the oracle comparison feeds each case's cameras, missing ones included.
  Scratch tmp("every");
  for (const char* family : {"pi0", "pi05"}) {
    for (const auto& entry : fs::directory_iterator(kFixtures / family)) {
      if (!entry.is_directory()) continue;
      const std::string label = std::string(family) + "/" + entry.path().filename().string();
      const fs::path out = tmp / (std::string(family) + "-" + entry.path().filename().string());
      const CliRun e = run_tether("export " + (entry.path() / "checkpoint").string() + " -o " + out.string());
      ASSERT_EQ(e.code, 0) << label << ": " << e.err;
      const CliRun v = run_tether("validate export " + out.string());
      EXPECT_EQ(v.code, 0) << label << ": " << v.out;
      EXPECT_NE(v.out.find("oracle-" + entry.path().filename().string()), std::string::npos) << label << ": " << v.out;
    }
  }
}

TEST_F(Pi0Cli, BadRequestInputExitsTwoWithOneLine) {
  struct Bad {
    const Case* c;
    std::string args, needle;
  };
  const std::string pi0 = kPi0.checkpoint().string(), pi05 = kPi05.checkpoint().string();
  const std::string pi0_image = " --image camera1=" + (kFixtures / "pi0/cam1_stats/inputs/camera1_0.png").string();
  const std::vector<Bad> cases = {
      {&kPi0, pi0 + pi0_image + " --state 1,2,3 --instruction go", "--state has 3 values, the model expects 6"},
      {&kPi05, pi05 + pi0_image + " --state 1,2,3,4,5,6 --instruction go", "--state has 6 values, the model expects 8"},
      {&kPi0, pi0 + pi0_image + " --state 1,2,3,4,5,6" + raw_instruction("pick \\377 it"),
       "instruction is not valid UTF-8 (byte 5 of 9)"},
      {&kPi05, pi05 + pi0_image + " --state 1,2,3,4,5,6,7,8" + raw_instruction("caf\\303"),
       "instruction is not valid UTF-8 (byte 3 of 4)"},
      {&kPi0, pi0 + " --image wrist=" + (kFixtures / "pi0/cam1_stats/inputs/camera1_0.png").string() +
                  " --state 1,2,3,4,5,6 --instruction go",
       "no camera 'wrist' (it has: observation.images.camera1)"},
      {&kPi0, pi0 + pi0_image + " --state=1,2,3,4,5,nan --instruction go", "state contains NaN or Inf"},
  };
  for (const auto& b : cases) {
    const CliRun r = run_tether("predict " + b.args);
    EXPECT_EQ(r.code, 2) << b.args << "\n" << r.err;
    EXPECT_NE(r.err.find(b.needle), std::string::npos) << b.args << "\n" << r.err;
    EXPECT_EQ(lines(r.err), 1) << r.err;
    EXPECT_TRUE(r.out.empty()) << r.out;
  }
}

TEST_F(Pi0Cli, BadCheckpointExitsTwoWithOneLineNamingTheFault) {
  Scratch tmp("bad_ckpt");
  const fs::path src = kPi0.checkpoint();
  struct Bad {
    fs::path dir;
    std::string needle;
  };
  std::vector<Bad> cases;
  // A state longer than the model's max_state_dim (the config of a copy edited; fixtures are never touched).
  const fs::path long_state = tmp / "long_state";
  fs::copy(src, long_state, fs::copy_options::recursive);
  edit_config(long_state, [](Json& c) { c["max_state_dim"] = 4; });
  cases.push_back({long_state, "config.json: the state has 6 values, more than max_state_dim 4"});
  const fs::path long_action = tmp / "long_action";
  fs::copy(src, long_action, fs::copy_options::recursive);
  edit_config(long_action, [](Json& c) { c["max_action_dim"] = 5; });
  cases.push_back({long_action, "config.json: the action has 6 values, more than max_action_dim 5"});
  // Weights: missing, truncated, not safetensors at all.
  const fs::path missing = tmp / "missing";
  fs::copy(src, missing, fs::copy_options::recursive);
  fs::remove(missing / "model.safetensors");
  cases.push_back({missing, "model.safetensors"});
  const fs::path truncated = tmp / "truncated";
  fs::copy(src, truncated, fs::copy_options::recursive);
  fs::resize_file(truncated / "model.safetensors", fs::file_size(truncated / "model.safetensors") / 2);
  cases.push_back({truncated, "file truncated?"});
  const fs::path garbage = tmp / "garbage";
  fs::copy(src, garbage, fs::copy_options::recursive);
  std::ofstream(garbage / "model.safetensors", std::ios::trunc) << "not a safetensors file at all";
  cases.push_back({garbage, (garbage / "model.safetensors").string()});
  // A tensor whose header shape disagrees with the model: the error names it.
  const std::string state_proj = "model.state_proj.weight";
  copy_with_shape(src, tmp / "state_proj", state_proj, {16, 64});
  cases.push_back({tmp / "state_proj", "tensor '" + state_proj + "' has shape [16, 64], the config implies [32, 32]"});
  const std::string down = "model.paligemma_with_expert.paligemma.model.language_model.layers.0.mlp.down_proj.weight";
  copy_with_shape(src, tmp / "down_proj", down, {128, 64});
  cases.push_back({tmp / "down_proj", "tensor '" + down + "' has shape [128, 64]"});
  const std::string q = "model.paligemma_with_expert.gemma_expert.model.layers.0.self_attn.q_proj.weight";
  copy_with_shape(src, tmp / "q_proj", q, {64, 64});
  cases.push_back({tmp / "q_proj", q + " has 64 rows; variant gemma_300m has 8 heads of 16"});
  // The unknown Gemma variant (head counts come from it).
  const fs::path variant = tmp / "variant";
  fs::copy(src, variant, fs::copy_options::recursive);
  edit_config(variant, [](Json& c) { c["action_expert_variant"] = "gemma_9b"; });
  cases.push_back({variant, "Gemma variant 'gemma_9b' (known: gemma_300m, gemma_2b)"});
  for (const auto& b : cases) {
    const CliRun r = run_tether("predict " + b.dir.string() + kPi0.observation());
    EXPECT_EQ(r.code, 2) << b.dir << "\n" << r.err;
    EXPECT_NE(r.err.find(b.needle), std::string::npos) << b.dir << "\n" << r.err;
    EXPECT_EQ(lines(r.err), 1) << r.err;
    EXPECT_TRUE(r.out.empty()) << r.out;
    // Serving fails the same way, before answering anything: the server exits with the one error line.
    const CliRun served = run_prefixed("timeout 120", "serve " + b.dir.string() + " --port 0");
    EXPECT_EQ(served.code, 2) << b.dir << "\n" << served.err;
    EXPECT_NE(served.err.find("error: "), std::string::npos) << served.err;
    EXPECT_NE(served.err.find(b.needle), std::string::npos) << served.err;
  }
}

TEST_F(Pi0Cli, Pi05CheckpointWithAStoredShapeMismatchNamesTheTensor) {
  Scratch tmp("pi05_shape");
  // lerobot's pi0.5 checkpoints keep the time MLP as time_mlp_* (pi0's are action_time_mlp_*); the message names the
  // tensor as the model knows it after lerobot's renames.
  const SafeTensorsFile f = SafeTensorsFile::open((kPi05.checkpoint() / "model.safetensors").string());
  std::string name;
  for (const auto& n : f.names())
    if (n.find("time_mlp_in.weight") != std::string::npos) name = n;
  ASSERT_FALSE(name.empty());
  const Shape& s = f.entry(name).shape;
  copy_with_shape(kPi05.checkpoint(), tmp / "ckpt", name, {s[1] * 2, s[0] / 2});
  const CliRun r = run_tether("predict " + (tmp / "ckpt").string() + kPi05.observation());
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("time_mlp_in.weight' has shape ["), std::string::npos) << r.err;
  EXPECT_EQ(lines(r.err), 1) << r.err;
}

TEST_F(Pi0Cli, AbsentOrUnreadableTokenizerExitsTwoWithOneLine) {
  Scratch tmp("tokenizer");
  const std::string snapshot_rel = fs::relative(kHubSnapshot, kHub).string();
  const auto hub_copy = [&](const std::string& name, const std::function<void(const fs::path&)>& damage) {
    const fs::path hub = tmp / name;
    fs::copy(kHub, hub, fs::copy_options::recursive);
    damage(hub / snapshot_rel);
    return hub;
  };
  struct Bad {
    fs::path hub;
    std::string needle;
  };
  const fs::path empty = tmp / "empty";
  fs::create_directories(empty);
  const std::vector<Bad> cases = {
      {empty, "'" + kTokenizerRepo + "' (the tokenizer_processor step's tokenizer_name of "},
      {hub_copy("bad_json", [](const fs::path& d) { std::ofstream(d / "tokenizer.json", std::ios::trunc) << "{\"model\": {"; }),
       "tokenizer.json: not valid JSON"},
      {hub_copy("bad_config", [](const fs::path& d) { std::ofstream(d / "tokenizer_config.json", std::ios::trunc) << "{"; }),
       "tokenizer_config.json: not valid JSON"},
      // Without tokenizer.json the SentencePiece model is read (transformers' slow path): a damaged one is named.
      {hub_copy("bad_model",
                [](const fs::path& d) {
                  fs::remove(d / "tokenizer.json");
                  fs::resize_file(d / "tokenizer.model", 100);
                }),
       "tokenizer.model: not a SentencePiece model"},
      {hub_copy("no_files",
                [](const fs::path& d) {
                  fs::remove(d / "tokenizer.json");
                  fs::remove(d / "tokenizer.model");
                }),
       "no tokenizer.json or tokenizer.model"},
  };
  for (const Case* c : {&kPi0, &kPi05}) {
    for (const auto& b : cases) {
      const CliRun r = run_with_hub(b.hub, "predict " + c->checkpoint().string() + c->observation());
      EXPECT_EQ(r.code, 2) << b.hub << "\n" << r.err;
      EXPECT_NE(r.err.find(b.needle), std::string::npos) << b.hub << "\n" << r.err;
      EXPECT_EQ(lines(r.err), 1) << r.err;
      EXPECT_TRUE(r.out.empty());
    }
  }
  // The copy beside the checkpoint is looked up first: a broken bundled tokenizer fails even with a good hub cache.
  const fs::path bundled = tmp / "bundled";
  fs::copy(kPi0.checkpoint(), bundled, fs::copy_options::recursive);
  fs::create_directories(bundled / kTokenizerRepo);
  fs::copy(kHubSnapshot, bundled / kTokenizerRepo, fs::copy_options::recursive);
  const CliRun good = run_tether("inspect model " + bundled.string() + " --json");
  ASSERT_EQ(good.code, 0) << good.err;
  EXPECT_EQ(Json::parse(good.out)["tokenizer_source"], (bundled / kTokenizerRepo / "tokenizer.json").string());
  std::ofstream(bundled / kTokenizerRepo / "tokenizer.json", std::ios::trunc) << "[";
  const CliRun r = run_tether("predict " + bundled.string() + kPi0.observation());
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find((bundled / kTokenizerRepo / "tokenizer.json").string() + ": not valid JSON"), std::string::npos)
      << r.err;
}
