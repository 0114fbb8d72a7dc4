// `tether models list|info`: the shipped registry's published figures and the FluxVLA entry, the registry file's
// validation (TETHER_REGISTRY), and the machine probe `tether go` prints before anything else.
#include <dlfcn.h>
#include <gtest/gtest.h>
#include <stdlib.h>

#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include "cli_runner.h"
#include "core/json_util.h"
#include "scratch_dir.h"

using namespace tether;
namespace fs = std::filesystem;

namespace {

// Runs tether with one environment variable set for the child only.
CliRun run_with_env(const std::string& var, const std::string& value, const std::string& args) {
  ::setenv(var.c_str(), value.c_str(), 1);
  CliRun r = run_tether(args);
  ::unsetenv(var.c_str());
  return r;
}

fs::path write_registry(const std::string& name, const std::string& text) {
  const fs::path dir = tether::testing::scratch_dir() / "models";
  fs::create_directories(dir);
  std::ofstream(dir / name) << text;
  return dir / name;
}

std::string line_with(const std::string& text, const std::string& needle) {
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);)
    if (line.find(needle) != std::string::npos) return line;
  return "";
}

const char* kGoodFigure =
    R"j({"benchmark": "LIBERO (average of 4 suites)", "metric": "success rate (%)", "value": 87.3,
        "setting": "fine-tuned on LIBERO", "source": {"title": "A paper", "url": "https://example.org/paper"}})j";

}  // namespace

TEST(ModelsCli, ListShowsTheHeadlineFigure) {
  const CliRun r = run_tether("models list");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(line_with(r.out, "id ").find("published"), std::string::npos) << r.out;
  EXPECT_NE(line_with(r.out, "smolvla-base").find("LIBERO 87.3%"), std::string::npos) << r.out;
  EXPECT_NE(line_with(r.out, "pi05-base").find("LIBERO 96.85%"), std::string::npos) << r.out;
  EXPECT_NE(line_with(r.out, "gr00t-n1.6").find("LIBERO-10 94.35%"), std::string::npos) << r.out;
  const std::string flux = line_with(r.out, "pi05-libero10-fluxvla");
  EXPECT_NE(flux.find("limxdynamics/FluxVLAEngine"), std::string::npos) << r.out;
  EXPECT_NE(flux.find("LIBERO-10 95.6%"), std::string::npos) << r.out;
  EXPECT_NE(flux.find("pi05_fluxvla"), std::string::npos) << r.out;
  EXPECT_NE(flux.find("supported"), std::string::npos) << r.out;
  EXPECT_EQ(flux.find("not yet"), std::string::npos) << r.out;
  EXPECT_NE(line_with(r.out, "smolvla-demo").find(" - "), std::string::npos) << r.out;
}

TEST(ModelsCli, EveryShippedEntryCitesItsFiguresOrSaysWhyNone) {
  const CliRun r = run_tether("models list --json");
  ASSERT_EQ(r.code, 0) << r.err;
  std::set<std::string> ids;
  for (const auto& m : Json::parse(r.out)) {
    const std::string id = m["id"];
    ids.insert(id);
    ASSERT_TRUE(m["figures"].is_array()) << id;
    if (m["figures"].empty()) {
      EXPECT_TRUE(m["figures_note"].is_string()) << id << ": no figures and no note";
      EXPECT_TRUE(m["published"].is_null()) << id;
    } else {
      EXPECT_TRUE(m["published"].is_string()) << id;
    }
    for (const auto& f : m["figures"]) {
      EXPECT_EQ(f["metric"], "success rate (%)") << id;
      EXPECT_GT(f["value"].get<double>(), 0) << id;
      EXPECT_LE(f["value"].get<double>(), 100) << id;
      EXPECT_EQ(f["source"]["url"].get<std::string>().rfind("https://", 0), 0u) << id;
      EXPECT_FALSE(f["source"]["title"].get<std::string>().empty()) << id;
      EXPECT_FALSE(f["setting"].get<std::string>().empty()) << id;
    }
  }
  for (const char* id : {"smolvla-demo", "smolvla-base", "pi0-base", "pi05-base", "pi05-libero10-fluxvla", "gr00t-n1.7", "gr00t-n1.6"})
    EXPECT_TRUE(ids.count(id)) << id;
}

TEST(ModelsCli, InfoPrintsEveryFigureWithItsSource) {
  const CliRun r = run_tether("models info smolvla-base");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("published    LIBERO (average of 4 suites): 87.3% success rate \u2014 SmolVLA 0.45B"),
            std::string::npos)
      << r.out;
  EXPECT_NE(r.out.find("published    Meta-World MT50 (average of 4 difficulty levels): 57.3% success rate"),
            std::string::npos)
      << r.out;
  EXPECT_NE(r.out.find("source: SmolVLA: A Vision-Language-Action Model for Affordable and Efficient Robotics"),
            std::string::npos)
      << r.out;
  EXPECT_NE(r.out.find("https://arxiv.org/abs/2506.01844"), std::string::npos) << r.out;
  const CliRun demo = run_tether("models info smolvla-demo");
  ASSERT_EQ(demo.code, 0) << demo.err;
  EXPECT_NE(demo.out.find("published    none: randomly initialised"), std::string::npos) << demo.out;
}

TEST(ModelsCli, FluxvlaEntryPointsAtItsFolderOfTheRepo) {
  const CliRun r = run_tether("models info pi05-libero10-fluxvla --json --target orin-64");
  ASSERT_EQ(r.code, 0) << r.err;
  const Json j = Json::parse(r.out);
  EXPECT_EQ(j["family"], "pi05_fluxvla");
  EXPECT_EQ(j["hf_repo"], "limxdynamics/FluxVLAEngine");
  EXPECT_EQ(j["subfolder"], "pi05_paligemma_libero_10_full_finetune_bs64");
  EXPECT_TRUE(j["supported"].get<bool>());
  EXPECT_EQ(j["published"], "LIBERO-10 95.6%");
  ASSERT_EQ(j["figures"].size(), 1u);
  EXPECT_EQ(j["figures"][0]["benchmark"], "LIBERO-10 / LIBERO-Long");
  EXPECT_DOUBLE_EQ(j["figures"][0]["value"].get<double>(), 95.6);
  EXPECT_NE(j["figures"][0]["source"]["url"].get<std::string>().find("github.com/limxdynamics/FluxVLA"),
            std::string::npos);
  const CliRun text = run_tether("models info pi05-libero10-fluxvla");
  EXPECT_NE(text.out.find("subfolder    pi05_paligemma_libero_10_full_finetune_bs64"), std::string::npos) << text.out;
}

TEST(ModelsCli, RegistryFigureErrorsNameTheEntryAndField) {
  const auto entry = [](const std::string& extra) {
    return R"({"models": {"ok": {"family": "smolvla", "hf_repo": "a/b", "figures": [)" + std::string(kGoodFigure) +
           R"(]}, "bad": {"family": "smolvla", "hf_repo": "a/c")" + extra + "}}}";
  };
  const std::string good = std::string(kGoodFigure);
  const auto with = [&](const std::string& from, const std::string& to) {
    std::string f = good;
    f.replace(f.find(from), from.size(), to);
    return ", \"figures\": [" + f + "]";
  };
  const std::vector<std::pair<std::string, std::string>> cases = {
      {", \"figures\": {}", "models.bad.figures: must be a list"},
      {", \"figures\": [3]", "models.bad.figures[0]: must be an object"},
      {with("\"value\": 87.3", "\"value\": \"87.3\""), "models.bad.figures[0]: field 'value' must be a number"},
      {with("\"value\": 87.3", "\"value\": 187.3"), "models.bad.figures[0]: field 'value' 187.3 is not a percentage"},
      {with("\"setting\": \"fine-tuned on LIBERO\"", "\"setting\": \"\""), "models.bad.figures[0]: field 'setting' is empty"},
      {with("\"metric\"", "\"metrc\""), "models.bad.figures[0]: missing field 'metric'"},
      {with(", \"source\": {\"title\": \"A paper\", \"url\": \"https://example.org/paper\"}", ""),
       "models.bad.figures[0]: missing field 'source'"},
      {with("https://example.org/paper", "example.org/paper"), "models.bad.figures[0].source: field 'url' is not an http(s)"},
      {with("\"title\": \"A paper\", ", ""), "models.bad.figures[0].source: missing field 'title'"},
      {", \"subfolder\": \"../x\"", "models.bad: 'subfolder' must be a relative folder"},
  };
  for (const auto& [extra, message] : cases) {
    const fs::path reg = write_registry("bad.json", entry(extra));
    const CliRun r = run_with_env("TETHER_REGISTRY", reg.string(), "models list");
    EXPECT_EQ(r.code, 2) << extra << "\n" << r.out;
    EXPECT_NE(r.err.find(reg.string() + ": " + message), std::string::npos) << extra << "\n" << r.err;
  }
  // The good entry alone loads, and an entry without figures shows "-".
  const fs::path reg = write_registry("good.json", entry(""));
  const CliRun r = run_with_env("TETHER_REGISTRY", reg.string(), "models list --json");
  ASSERT_EQ(r.code, 0) << r.err;
  const Json j = Json::parse(r.out);
  EXPECT_EQ(j[0]["published"], "LIBERO 87.3%");
  EXPECT_TRUE(j[1]["published"].is_null());
  EXPECT_TRUE(j[1]["figures"].empty());
  fs::remove_all(reg.parent_path());
}

TEST(GoProbe, PrintsTheMachineBeforeAnythingElse) {
  // A model that cannot be pulled (offline, nothing in an empty cache) fails after the probe: the probe lines come
  // first, then the one error line. Offline, so that the test never starts a real multi-gigabyte download.
  const fs::path cache = tether::testing::scratch_dir() / "go_probe_empty";
  ::setenv("HF_HUB_CACHE", cache.c_str(), 1);
  ::setenv("HF_HUB_OFFLINE", "1", 1);
  const CliRun r = run_tether("go --model pi05-base");
  ::unsetenv("HF_HUB_CACHE");
  ::unsetenv("HF_HUB_OFFLINE");
  fs::remove_all(cache);
  EXPECT_NE(r.err.find("not on disk and could not be downloaded"), std::string::npos) << r.err;
  EXPECT_EQ(r.code, 2) << r.err;
  const std::string cpu = line_with(r.err, "tether go: CPU: ");
  const std::string gpu = line_with(r.err, "tether go: GPU: ");
  EXPECT_NE(cpu.find(" cores; memory: "), std::string::npos) << r.err;
  EXPECT_FALSE(gpu.empty()) << r.err;
  EXPECT_LT(r.err.find("tether go: GPU: "), r.err.find("error:")) << r.err;
  if (void* h = dlopen("libcuda.so.1", RTLD_NOW | RTLD_LOCAL); !h)  // this machine has no GPU driver
    EXPECT_EQ(gpu, "tether go: GPU: none found (no NVIDIA driver: libcuda.so.1 not found); serving on CPU") << r.err;
  else
    EXPECT_NE(gpu.find("serving on CPU"), std::string::npos) << r.err;
}

TEST(GoProbe, SaysWhyThePrecisionWasPicked) {
  // A supported entry that is not on disk: go probes, picks the precision, then fails to pull (offline) with exit 2.
  const fs::path cache = tether::testing::scratch_dir() / "go_probe";
  const fs::path reg = write_registry(
      "go.json", R"({"models": {"small": {"family": "smolvla", "hf_repo": "tether-test/small", "supported": true,
                                          "parameters": 1000000},
                                "huge": {"family": "smolvla", "hf_repo": "tether-test/huge", "supported": true,
                                         "parameters": 1000000000000000}}})");
  ::setenv("HF_HUB_CACHE", cache.string().c_str(), 1);
  ::setenv("HF_HUB_OFFLINE", "1", 1);
  // Capped at AVX2 or NEON (no bf16 instructions), so memory alone decides, whatever CPU runs the test.
  ::setenv("TETHER_MAX_CPU_ISA", kLowerIsaCaps[0], 1);
  const CliRun small = run_with_env("TETHER_REGISTRY", reg.string(), "go --model small");
  const CliRun huge = run_with_env("TETHER_REGISTRY", reg.string(), "go --model huge");
  const CliRun asked = run_with_env("TETHER_REGISTRY", reg.string(), "go --model huge --precision fp32");
  ::unsetenv("HF_HUB_CACHE");
  ::unsetenv("HF_HUB_OFFLINE");
  ::unsetenv("TETHER_MAX_CPU_ISA");
  for (const CliRun* r : {&small, &huge, &asked}) {
    EXPECT_EQ(r->code, 2) << r->err;
    EXPECT_NE(r->err.find("not on disk and could not be downloaded"), std::string::npos) << r->err;
  }
  EXPECT_NE(small.err.find("tether go: precision fp32 (the reference): small needs about 5.0 MB, "), std::string::npos)
      << small.err;
  EXPECT_NE(huge.err.find("tether go: huge does not fit in fp32 here ("), std::string::npos) << huge.err;
  EXPECT_NE(huge.err.find("): using bf16"), std::string::npos) << huge.err;
  EXPECT_NE(asked.err.find("tether go: precision fp32: asked with --precision"), std::string::npos) << asked.err;
  fs::remove_all(reg.parent_path());
  fs::remove_all(cache);
}
