// `tether export`: a self-contained deployment directory (weights in the chosen precision, config, and what the
// family's ExportPlan says the model needs: normalisation stats, backbone tokenizer and config) plus
// VERIFICATION.md, a receipt of what was exported and how far the export is from the fp32 source on seeded inputs
// (and from upstream when the source is an oracle fixture).
// Deterministic: exporting the same input twice gives byte-identical files.
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <set>

#include "cli/commands.h"
#include "cli/observation_args.h"
#include "cli/registry.h"
#include "cli/serve_flags.h"
#include "cli/verify.h"
#include "core/hash.h"
#include "core/safetensors.h"
#include "models/family.h"
#include "policy/embodiment.h"
#include "runtime/wedges.h"

namespace tether::cli {

namespace fs = std::filesystem;

namespace {

struct ExportArgs {
  std::string source, out, precision = "fp32", target, embodiment, custom_embodiment, embodiment_tag;
  std::string backend = "cpu";  // where the export's verification runs
};

// The source as a directory: a checkpoint directory, or a registry id whose checkpoint is on disk.
std::string resolve_source(const std::string& source) {
  if (fs::is_directory(source)) return fs::path(source).lexically_normal().string();
  const Registry reg = Registry::load();
  const RegistryEntry& e = reg.get(source);
  if (auto dir = local_checkpoint(e)) return *dir;
  throw Error(ErrorCode::not_found, source + ": not on disk yet (tether models pull " + source + ")");
}

// Floating-point tensors converted to `precision` (except those in `keep`); everything else copied as is. Names stay
// sorted.
void convert_weights(const std::string& in, const std::string& out, const std::string& precision,
                     const std::set<std::string>& keep) {
  const SafeTensorsFile f = SafeTensorsFile::open(in);
  std::map<std::string, Tensor> tensors;
  std::vector<std::shared_ptr<std::vector<uint16_t>>> halves;
  for (const auto& name : f.names()) {
    Tensor t = f.get(name);
    const bool floating = t.dtype == DType::f32 || t.dtype == DType::bf16 || t.dtype == DType::f16;
    if (!floating || precision == "fp32" || keep.count(name)) {
      if (floating && t.dtype != DType::f32) t = Tensor::from_f32(t.shape, t.to_f32());
      tensors[name] = t;
      continue;
    }
    const std::vector<float> v = t.to_f32();
    auto buf = std::make_shared<std::vector<uint16_t>>(v.size());
    for (std::size_t i = 0; i < v.size(); ++i) (*buf)[i] = precision == "bf16" ? f32_to_bf16(v[i]) : f32_to_f16(v[i]);
    halves.push_back(buf);
    tensors[name] = Tensor{precision == "bf16" ? DType::bf16 : DType::f16, t.shape, buf->data(), buf};
  }
  std::map<std::string, std::string> meta = f.metadata();
  meta["format"] = "pt";
  write_safetensors(out, tensors, meta);
}

std::string table(const std::vector<CaseDiff>& diffs) {
  std::ostringstream s;
  s << "| case | values | max \\|diff\\| | mean \\|diff\\| |\n|---|---|---|---|\n";
  char buf[128];
  for (const auto& d : diffs) {
    std::snprintf(buf, sizeof buf, "| %s | %lld | %.3e | %.3e |\n", d.name.c_str(), (long long)d.values, d.max_abs,
                  d.mean_abs);
    s << buf;
  }
  return s.str();
}

}  // namespace

double export_checkpoint(const std::string& src, const std::string& out_dir, const std::string& precision,
                         const std::string& target_id, const std::string& embodiment_file,
                         const std::string& embodiment_tag, const std::string& backend) {
  const ExportArgs a{src, out_dir, precision, target_id, "", "", embodiment_tag};
  const models::LoadOptions source_options = load_options("fp32", embodiment_tag, backend);
  // Validated before anything is written; its joint count is checked against the model once it is loaded.
  const std::optional<policy::Embodiment> embodiment =
      embodiment_file.empty() ? std::nullopt : std::optional(policy::load_embodiment_file(embodiment_file));
  const fs::path out(a.out);
  if (fs::exists(out) && !fs::is_directory(out)) throw Error(ErrorCode::invalid_argument, a.out + ": exists and is not a directory");
  const Json target = a.target.empty() ? Json(nullptr) : deployment_target(a.target);

  // What the family says the export carries (models/family.h); the receipt names exactly what was exported.
  const fs::path src_dir(src);
  const models::FamilyDescriptor& family = models::recognise(src_dir);
  const std::vector<std::string> weights = family.weight_files(src_dir);
  if (weights.empty()) throw Error(ErrorCode::not_found, src + ": no weights (" + models::kSingleWeightsFile + " or " +
                                                             models::kShardIndexFile + ")");
  const Json config = read_json_file((src_dir / "config.json").string());
  const models::ExportPlan plan = family.export_plan(src_dir, config, source_options);
  std::vector<std::string> names = {"config.json"};
  names.insert(names.end(), weights.begin(), weights.end());
  names.insert(names.end(), plan.copy.begin(), plan.copy.end());
  for (const auto& [name, content] : plan.written) names.push_back(name);
  std::sort(names.begin(), names.end());  // a deterministic receipt
  names.erase(std::unique(names.begin(), names.end()), names.end());
  Json source_files = Json::object();
  for (const auto& name : names) source_files[name] = sha256_file_hex((src_dir / name).string());

  auto reference = policy::Policy::load(src, source_options);
  if (embodiment) runtime::embodiment_action_dim(*embodiment, reference->spec());  // the rule `tether serve` applies

  // Write the deployment directory.
  fs::create_directories(out);
  for (const auto& name : plan.copy) {
    fs::create_directories((out / name).parent_path());  // a family's files may sit in sub-directories
    fs::copy_file(src_dir / name, out / name, fs::copy_options::overwrite_existing);
  }
  for (const auto& bundle : plan.bundles) {
    fs::create_directories(out / bundle.to);
    for (const auto& name : bundle.files)
      fs::copy_file(bundle.from / name, out / bundle.to / name, fs::copy_options::overwrite_existing);
  }
  std::ofstream(out / "config.json", std::ios::binary | std::ios::trunc) << plan.config.dump(4) << "\n";
  for (const auto& [name, content] : plan.written) {
    fs::create_directories((out / name).parent_path());
    std::ofstream(out / name, std::ios::binary | std::ios::trunc) << content.dump(4) << "\n";
  }
  const std::set<std::string> keep(plan.keep_dtype.begin(), plan.keep_dtype.end());
  for (const auto& name : weights) {
    fs::create_directories((out / name).parent_path());
    if (name.ends_with(".safetensors")) convert_weights((src_dir / name).string(), (out / name).string(), a.precision, keep);
    else fs::copy_file(src_dir / name, out / name, fs::copy_options::overwrite_existing);  // the shard index
  }
  if (embodiment) fs::copy_file(embodiment_file, out / kExportEmbodimentFile, fs::copy_options::overwrite_existing);
  else fs::remove(out / kExportEmbodimentFile);

  // Measure the export against the fp32 source (and upstream, when the source is an oracle fixture).
  auto exported = policy::Policy::load(out.string(), source_options);
  const std::vector<CaseDiff> seeded = compare_seeded(*reference, *exported, 4);
  const std::vector<CaseDiff> oracle = compare_with_oracle(src, *exported);

  Json files = Json::object();
  std::vector<fs::path> outputs;
  for (const auto& e : fs::recursive_directory_iterator(out))
    if (e.is_regular_file() && e.path().filename() != "VERIFICATION.md" && e.path().filename() != "tether_export.json")
      outputs.push_back(e.path());
  std::sort(outputs.begin(), outputs.end());
  for (const auto& p : outputs) files[fs::relative(p, out).string()] = sha256_file_hex(p.string());
  Json diffs = Json::array();
  for (const auto* group : {&seeded, &oracle})
    for (const auto& d : *group) diffs.push_back({{"case", d.name}, {"max_abs", d.max_abs}, {"mean_abs", d.mean_abs}});
  const Json manifest = {{"tether_version", TETHER_VERSION},
                         {"source", {{"path", fs::absolute(src).lexically_normal().string()}, {"files", source_files}}},
                         {"precision", a.precision},
                         {"target", target},
                         {"embodiment", embodiment ? Json(embodiment->name) : Json(nullptr)},
                         {"embodiment_tag", embodiment_tag.empty() ? Json(nullptr) : Json(embodiment_tag)},
                         {"files", files},
                         {"verification", diffs}};
  std::ofstream(out / "tether_export.json", std::ios::binary | std::ios::trunc) << manifest.dump(2) << "\n";

  std::ostringstream md;
  md << "# Verification receipt\n\n"
     << "Exported by Tether " << TETHER_VERSION << " (`tether export`), precision **" << a.precision << "**"
     << (target.is_null() ? std::string() : ", target **" + a.target + "**")
     << (embodiment ? ", embodiment **" + embodiment->name + "** (`" + kExportEmbodimentFile + "`, used by `tether serve`)" : "")
     << (embodiment_tag.empty() ? std::string()
                                : ", embodiment tag **" + embodiment_tag + "** (the only one whose statistics it holds)")
     << ".\n\n"
     << "## Source\n\n`" << fs::absolute(src).lexically_normal().string() << "`\n\n| file | sha256 |\n|---|---|\n";
  for (auto it = source_files.begin(); it != source_files.end(); ++it) md << "| " << it.key() << " | " << it->get<std::string>() << " |\n";
  for (const auto& bundle : plan.bundles)
    md << "\nBackbone files copied from `" << bundle.from.string() << "` into `" << bundle.to << "/`.\n";
  md << "\n## Output files\n\n| file | sha256 |\n|---|---|\n";
  for (auto it = files.begin(); it != files.end(); ++it) md << "| " << it.key() << " | " << it->get<std::string>() << " |\n";
  md << "\n## Measured difference\n\nAction chunks (robot units) of the export against the fp32 source, both run by Tether in float32 "
        "on seeded inputs (pseudo-random frames, states and noise):\n\n"
     << table(seeded);
  if (!oracle.empty())
    md << "\nAgainst the upstream PyTorch outputs recorded in the oracle fixture next to the source:\n\n" << table(oracle);
  md << "\nRe-check at any time with `tether validate export <this directory>`.\n";
  std::ofstream(out / "VERIFICATION.md", std::ios::binary | std::ios::trunc) << md.str();

  double worst = 0;
  for (const auto* group : {&seeded, &oracle})
    for (const auto& d : *group) worst = std::max(worst, d.max_abs);
  return worst;
}

namespace {

int run_export(const ExportArgs& a) {
  const std::string src = resolve_source(a.source);
  if (!a.embodiment.empty() && !a.custom_embodiment.empty())
    throw Error(ErrorCode::invalid_argument, "give --embodiment or --custom-embodiment-config, not both");
  const std::string embodiment = !a.custom_embodiment.empty() ? a.custom_embodiment
                                 : a.embodiment.empty()       ? std::string()
                                                              : embodiment_preset_file(a.embodiment);
  const double worst = export_checkpoint(src, a.out, a.precision, a.target, embodiment, a.embodiment_tag, a.backend);
  std::printf("exported %s -> %s (%s); max |diff| against the source %.3e; receipt: %s\n", src.c_str(), a.out.c_str(),
              a.precision.c_str(), worst, (fs::path(a.out) / "VERIFICATION.md").string().c_str());
  return kExitOk;
}

}  // namespace

Verb add_export(CLI::App& app) {
  auto args = std::make_shared<ExportArgs>();
  CLI::App* sub = app.add_subcommand("export", "Write a self-contained deployment directory with a VERIFICATION.md receipt");
  sub->add_option("source", args->source, "Checkpoint directory or registry id")->required();
  sub->add_option("-o,--output", args->out, "Export directory")->required();
  sub->add_option("--precision", args->precision, "Weights precision: fp32, bf16 or fp16")
      ->check(CLI::IsMember({"fp32", "bf16", "fp16"}))
      ->capture_default_str();
  sub->add_option("--target", args->target, "Deployment target (see tether inspect targets), recorded in the receipt");
  sub->add_option("--embodiment", args->embodiment, "Embodiment preset the export carries (franka, so100, ur5, quadcopter)");
  sub->add_option("--custom-embodiment-config", args->custom_embodiment, "Embodiment JSON file the export carries");
  add_embodiment_tag_flag(sub, args->embodiment_tag);
  add_backend_flag(sub, args->backend);
  return {sub, [args] { return run_export(*args); }};
}

}  // namespace tether::cli
