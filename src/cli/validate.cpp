// `tether validate export`: re-checks an export directory: its files against the hashes in its manifest, and its
// action chunks against the reference checkpoint (fp32) on seeded inputs and against upstream's outputs when the
// reference is an oracle fixture. Exit 0 when every check passes, 1 when one fails, 2 on a usage error.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>

#include "cli/commands.h"
#include "cli/observation_args.h"
#include "cli/verify.h"
#include "core/hash.h"

namespace tether::cli {

namespace fs = std::filesystem;

namespace {

struct ValidateArgs {
  std::string export_dir, reference, output_json, init_ci;
  double threshold = 1e-4;
  std::string backend = "cpu";
};

int write_ci(const ValidateArgs& a, const std::string& reference) {
  const fs::path path = a.init_ci;
  fs::create_directories(path.parent_path().empty() ? fs::path(".") : path.parent_path());
  std::ofstream out(path, std::ios::trunc);
  out << "# Written by `tether validate export --init-ci`: fails the pipeline when the exported policy drifts from its\n"
      << "# reference by more than the threshold, or when an exported file changed.\n"
      << "name: tether-validate\n"
      << "on: [push, pull_request]\n"
      << "jobs:\n"
      << "  validate:\n"
      << "    runs-on: ubuntu-latest\n"
      << "    steps:\n"
      << "      - uses: actions/checkout@v4\n"
      << "      - name: Validate the exported policy\n"
      << "        run: tether validate export " << a.export_dir << " --reference " << reference << " --threshold "
      << a.threshold << " --output-json validation.json\n";
  if (!out) throw Error(ErrorCode::io, path.string() + ": cannot write");
  std::printf("wrote %s\n", path.string().c_str());
  return kExitOk;
}

int run_validate(const ValidateArgs& a) {
  const fs::path dir(a.export_dir);
  const fs::path manifest_path = dir / "tether_export.json";
  if (!fs::exists(manifest_path))
    throw Error(ErrorCode::invalid_argument, a.export_dir + ": not a Tether export (no tether_export.json)");
  const Json manifest = read_json_file(manifest_path.string());
  const std::string reference =
      a.reference.empty() ? json_get<std::string>(json_get<Json>(manifest, "source", manifest_path.string()), "path",
                                                  manifest_path.string())
                          : a.reference;
  if (!fs::is_directory(reference))
    throw Error(ErrorCode::not_found, reference + ": reference checkpoint not found (give --reference)");
  if (!a.init_ci.empty()) return write_ci(a, reference);

  Json rows = Json::array();
  bool ok = true;
  auto add = [&](const std::string& check, double max_abs, double mean_abs, bool pass) {
    rows.push_back({{"check", check}, {"max_abs", max_abs}, {"mean_abs", mean_abs}, {"pass", pass}});
    ok &= pass;
  };
  // Integrity: every file the export wrote, unchanged.
  const Json files = json_get<Json>(manifest, "files", manifest_path.string());
  std::size_t altered = 0;
  for (auto it = files.begin(); it != files.end(); ++it) {
    const fs::path p = dir / it.key();
    const bool same = fs::exists(p) && sha256_file_hex(p.string()) == it->get<std::string>();
    if (!same) {
      ++altered;
      add("file " + it.key() + (fs::exists(p) ? " altered" : " missing"), 0, 0, false);
    }
  }
  if (altered == 0) add("files (" + std::to_string(files.size()) + ") match their sha256", 0, 0, true);

  // A damaged export may not even load: that is a failed check, reported with the rest, not a usage error. The
  // reference failing to load (its tokenizer no longer in the hub cache, say) is told apart from the export's failure.
  // An export of one embodiment of a multi-embodiment checkpoint (GR00T) is compared on that embodiment.
  const Json tag = manifest.value("embodiment_tag", Json(nullptr));
  const models::LoadOptions options = load_options("fp32", tag.is_string() ? tag.get<std::string>() : "", a.backend);
  std::unique_ptr<policy::Policy> ref;
  try {
    ref = policy::Policy::load(reference, options);
  } catch (const Error& e) {
    add(std::string("load the reference: ") + e.what(), INFINITY, INFINITY, false);
  }
  try {
    if (ref) {
      auto exported = policy::Policy::load(dir.string(), options);
      for (const auto& d : compare_seeded(*ref, *exported, 4))
        add(d.name, d.max_abs, d.mean_abs, d.max_abs <= a.threshold);
      for (const auto& d : compare_with_oracle(reference, *exported))
        add(d.name, d.max_abs, d.mean_abs, d.max_abs <= a.threshold);
    }
  } catch (const Error& e) {
    add(std::string("run the export: ") + e.what(), INFINITY, INFINITY, false);
  }

  std::printf("%-44s %12s %12s  %s\n", "check", "max |diff|", "mean |diff|", "result");
  for (const auto& r : rows)
    std::printf("%-44s %12.3e %12.3e  %s\n", r["check"].get<std::string>().c_str(), r["max_abs"].get<double>(),
                r["mean_abs"].get<double>(), r["pass"].get<bool>() ? "PASS" : "FAIL");
  std::printf("%s (threshold %.1e, reference %s)\n", ok ? "PASS" : "FAIL", a.threshold, reference.c_str());
  if (!a.output_json.empty()) {
    std::ofstream out(a.output_json, std::ios::trunc);
    out << Json{{"export", a.export_dir}, {"reference", reference}, {"threshold", a.threshold}, {"pass", ok}, {"checks", rows}}.dump(2)
        << "\n";
    if (!out) throw Error(ErrorCode::io, a.output_json + ": cannot write");
  }
  return ok ? kExitOk : kExitCheckFailed;
}

}  // namespace

Verb add_validate(CLI::App& app) {
  auto args = std::make_shared<ValidateArgs>();
  CLI::App* sub = app.add_subcommand("validate", "Check an export against its reference");
  sub->require_subcommand(1);
  CLI::App* exp = sub->add_subcommand("export", "Files against their recorded hashes, actions against the reference");
  exp->add_option("export_dir", args->export_dir, "Directory written by tether export")->required();
  exp->add_option("--reference", args->reference, "Reference checkpoint (default: the export's recorded source)");
  exp->add_option("--threshold", args->threshold, "Largest max |diff| (robot units) that passes")->capture_default_str();
  exp->add_option("--output-json", args->output_json, "Also write the results as JSON");
  add_backend_flag(exp, args->backend);
  exp->add_option("--init-ci", args->init_ci, "Write a CI workflow running this check to the given path, e.g. .github/workflows/tether-validate.yml");
  return {sub, [args] { return run_validate(*args); }};
}

}  // namespace tether::cli
