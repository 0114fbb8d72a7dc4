// `tether doctor`: what this machine offers Tether, each check with a one-line remediation when it fails.
// CUDA libraries are probed with dlopen, so doctor runs (and says so) on machines without them.
#include <algorithm>
#include <sys/statvfs.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <iostream>

#if defined(__x86_64__)
#include <cpuid.h>
#endif

#include "backend/backend.h"
#include "backend/cpu/cpu_features.h"
#include "backend/cpu/gemm.h"
#include "backend/cpu/packed_linear.h"
#include "cli/commands.h"
#include "cli/hardware.h"
#include "core/hf_paths.h"
#include "core/json_util.h"
#include "core/safetensors.h"
#include "models/family.h"

namespace tether::cli {

namespace fs = std::filesystem;

namespace {

enum class Status { ok, warn, fail, skip };

struct Check {
  std::string group, name;
  Status status;
  std::string detail, remedy;
};

const char* mark(Status s) {
  switch (s) {
    case Status::ok: return "\u2713";
    case Status::warn: return "!";
    case Status::fail: return "\u2717";
    case Status::skip: return "-";
  }
  return "?";
}

const char* status_name(Status s) {
  switch (s) {
    case Status::ok: return "ok";
    case Status::warn: return "warn";
    case Status::fail: return "fail";
    case Status::skip: return "skip";
  }
  return "?";
}

std::string gb(double bytes) {
  char buf[32];
  if (bytes < 1e9) std::snprintf(buf, sizeof buf, "%.1f MB", bytes / 1e6);
  else std::snprintf(buf, sizeof buf, "%.1f GB", bytes / 1e9);
  return buf;
}

std::string count_str(int64_t n) {
  char buf[32];
  if (n >= 1000000) std::snprintf(buf, sizeof buf, "%.1fM", double(n) / 1e6);
  else std::snprintf(buf, sizeof buf, "%.1fK", double(n) / 1e3);
  return buf;
}

void cpu_checks(std::vector<Check>& out) {
  out.push_back({"cpu", "processor", Status::ok, cpu_model() + ", " + std::to_string(sysconf(_SC_NPROCESSORS_ONLN)) + " cores", ""});
#if defined(__x86_64__)
  __builtin_cpu_init();
  const bool avx2 = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  const bool avx512 = __builtin_cpu_supports("avx512f");
  unsigned a = 0, b = 0, c = 0, d = 0;
  __cpuid_count(7, 1, a, b, c, d);
  const bool avx512_bf16 = (a >> 5) & 1;
  __cpuid_count(7, 0, a, b, c, d);
  const bool amx_bf16 = (d >> 22) & 1, amx_tile = (d >> 24) & 1;
  out.push_back({"cpu", "AVX2 + FMA", avx2 ? Status::ok : Status::fail, avx2 ? "present" : "missing",
                 "Tether's CPU kernels need an x86-64-v3 processor (AVX2, FMA) or newer"});
  out.push_back({"cpu", "AVX-512", avx512 ? Status::ok : Status::warn, avx512 ? "present (used by oneDNN and the kernels)" : "absent",
                 "fine; AVX-512 processors run the float32 GEMMs about 2x faster"});
  // Present is not the same as used: bf16 GEMMs run natively only where they beat fp32 (cpu_features.h).
  const std::string bf16_use = cpu::cpu_paths().native_bf16 ? "present (native bf16 GEMMs)"
                                                            : "present, not used: " + cpu::bf16_widened_reason();
  out.push_back({"cpu", "AVX-512 BF16", avx512_bf16 ? Status::ok : Status::skip, avx512_bf16 ? bf16_use : "absent",
                 ""});
  out.push_back({"cpu", "AMX", amx_tile && amx_bf16 ? Status::ok : Status::skip,
                 amx_tile && amx_bf16 ? "present (AMX-BF16 tiles)" : "absent", ""});
#if defined(__AVX512F__)
  const bool build_ok = avx512;
  const char* build = "this build targets AVX-512 (TETHER_NATIVE=ON: -march=native at build time)";
#else
  const bool build_ok = avx2;
  const char* build = "this build targets x86-64-v3 (AVX2); wider paths are chosen at run time";
#endif
  out.push_back({"cpu", "build target", build_ok ? Status::ok : Status::fail, build,
                 "rebuild on this machine: scripts/setup.sh (a TETHER_NATIVE build runs only on its build machine's CPU)"});
#elif defined(__aarch64__)
  out.push_back({"cpu", "NEON", Status::ok, "present (AArch64)", ""});
#endif
  // The paths this CPU gets, after TETHER_MAX_CPU_ISA / ONEDNN_MAX_CPU_ISA.
  try {
    out.push_back({"cpu", "dispatch", Status::ok, cpu::cpu_paths_summary(), ""});
    for (cpu::Precision p : {cpu::Precision::fp32, cpu::Precision::bf16, cpu::Precision::fp16})
      out.push_back({"cpu", std::string("--precision ") + cpu::precision_name(p), Status::ok,
                     cpu::compute_mode_description(p), ""});
  } catch (const Error& e) {
    out.push_back({"cpu", "dispatch", Status::fail, e.what(), "fix or unset TETHER_MAX_CPU_ISA"});
  }
  const char* omp = std::getenv("OMP_NUM_THREADS");
  out.push_back({"cpu", "GEMM library", Status::ok,
                 std::string(cpu::blas_name()) + ", " + std::to_string(cpu::blas_threads()) + " threads" +
                     (omp ? std::string(" (OMP_NUM_THREADS=") + omp + ")" : ""),
                 ""});
}

void memory_checks(std::vector<Check>& out) {
  const int64_t total = meminfo_bytes("MemTotal"), avail = meminfo_bytes("MemAvailable");
  const bool ok = avail > int64_t(2) * 1024 * 1024 * 1024;
  out.push_back({"memory", "RAM", ok ? Status::ok : Status::warn,
                 gb(double(avail)) + " available of " + gb(double(total)),
                 "a full-size model needs several GB in float32 (SmolVLA: about 1.5 GB); close other processes or use a smaller model"});
  for (const auto& [label, dir] :
       {std::pair<std::string, fs::path>{"model cache", fs::path(hf_hub_cache())}}) {
    fs::path probe = dir;
    while (!probe.empty() && !fs::exists(probe)) probe = probe.parent_path();
    struct statvfs st {};
    if (probe.empty() || statvfs(probe.c_str(), &st) != 0) {
      out.push_back({"disk", label, Status::warn, dir.string() + ": cannot stat", "create the directory or set HF_HUB_CACHE"});
      continue;
    }
    const double free_bytes = double(st.f_bavail) * double(st.f_frsize);
    out.push_back({"disk", label, free_bytes > 5e9 ? Status::ok : Status::warn, dir.string() + ": " + gb(free_bytes) + " free",
                   "free space or point HF_HUB_CACHE at a larger disk (checkpoints take 1-10 GB)"});
  }
}

void cuda_checks(std::vector<Check>& out) {
  const GpuProbe gpu = probe_gpus();
  if (gpu.driver_library.empty()) {
    out.push_back({"cuda", "driver", Status::skip, "no NVIDIA driver (libcuda.so.1 not found): CPU only",
                   "install the NVIDIA driver to use a GPU"});
  } else if (!gpu.driver_ok) {
    out.push_back({"cuda", "driver", Status::fail, gpu.driver_library + " loaded but cuInit failed",
                   "check the driver installation (nvidia-smi) and the device permissions"});
  } else {
    out.push_back({"cuda", "driver", Status::ok, "CUDA driver API " + cuda_version_str(gpu.driver_version), ""});
    for (std::size_t i = 0; i < gpu.devices.size(); ++i) {
      const GpuDevice& g = gpu.devices[i];
      out.push_back({"cuda", "GPU " + std::to_string(i),
                     supported_compute_capability(g.cc_major, g.cc_minor) ? Status::ok : Status::warn,
                     g.name + ", compute capability " + std::to_string(g.cc_major) + "." + std::to_string(g.cc_minor) +
                         (g.memory_bytes > 0 ? ", " + gb(double(g.memory_bytes)) : "") +
                         (g.free_bytes >= 0 ? " (" + gb(double(g.free_bytes)) + " free)" : ""),
                     "this GPU's compute capability is outside the supported table (8.0+); the CPU backend still works"});
    }
  }
  {
    // Whether this binary can run a model on the GPU: the backend compiled in, and a device it has code for.
    const auto compiled = backend::compiled_backends();
    const bool built = std::find(compiled.begin(), compiled.end(), "cuda") != compiled.end();
    std::string why;
    const bool usable = backend::backend_usable("cuda", &why);
    // A warning only where there is a GPU the backend cannot use; on a machine without one it is just skipped.
    out.push_back({"cuda", "backend", usable ? Status::ok : built && !gpu.devices.empty() ? Status::warn : Status::skip,
                   usable ? "compiled in and usable: --backend cuda (or auto) runs models on the GPU" : why,
                   built ? "a GPU with a driver is needed for --backend cuda; the CPU backend still works"
                         : "build with the CUDA toolkit (nvcc 12.6 or newer) for the GPU backend"});
  }
  const CudaLibraries libs = probe_cuda_libraries();
  const auto library_check = [&](const std::string& name, const CudaLibrary& lib, const std::string& soname,
                                 const std::string& version_prefix, const std::string& remedy) {
    if (lib.file.empty()) {
      out.push_back({"cuda", name, Status::skip, soname + " not found", remedy});
      return;
    }
    out.push_back({"cuda", name, lib.version.empty() ? Status::warn : Status::ok,
                   lib.file + (lib.version.empty() ? "" : ", " + version_prefix + lib.version), ""});
  };
  library_check("runtime", libs.runtime, "libcudart", "CUDA ", "install the CUDA toolkit runtime (12 or 13)");
  library_check("cuBLAS", libs.cublas, "libcublas", "version ", "install cuBLAS with the CUDA toolkit");
  library_check("cuDNN", libs.cudnn, "libcudnn", "version ", "optional; install cuDNN 9 for the GPU vision kernels");
}

void model_checks(const std::string& dir, std::vector<Check>& out) {
  const fs::path d(dir);
  const bool has_config = fs::exists(d / "config.json");
  out.push_back({"model", "config.json", has_config ? Status::ok : Status::fail,
                 has_config ? (d / "config.json").string() : (d / "config.json").string() + " missing",
                 "point at a checkpoint directory (it has config.json and its weights)"});
  // The family decides where the weights are and how the normaliser is read; without one, the conventional names.
  const models::FamilyDescriptor* family = nullptr;
  if (has_config) {
    try {
      family = &models::recognise(d);
      out.push_back({"model", "family", Status::ok, family->name + " (" + family->recognition + ")", ""});
    } catch (const Error& e) {
      out.push_back({"model", "family", Status::fail, e.what(), "use a checkpoint of a supported family"});
    }
  }
  const std::vector<std::string> files =
      family ? family->weight_files(d) : models::TensorStore::files_in(d.string());
  if (files.empty()) {
    out.push_back({"model", "weights", Status::fail,
                   (d / models::kSingleWeightsFile).string() + " missing (nor a " + models::kShardIndexFile + ")",
                   "point at a checkpoint directory with its weights (model.safetensors, or an index and its shards)"});
    return;
  }
  try {
    models::TensorStore store = family ? family->open_weights(d) : models::TensorStore::open_dir(d.string());
    int64_t params = 0, kept = 0, kept_bf16 = 0;
    for (const auto& name : store.names()) {
      const auto& entry = store.entry(name);
      const int64_t n = shape_numel(entry.shape);
      params += n;
      if (family && family->keeps_copy && !family->keeps_copy(name)) continue;
      kept += n;
      if (entry.dtype == DType::bf16) kept_bf16 += n;
    }
    double bytes = 0;
    for (const auto& f : files) bytes += double(fs::file_size(d / f));
    // The tensors the model keeps a copy of, at 4 bytes each in fp32 (2 for bf16-stored ones, kept as bf16 panels
    // exactly) and 2 in bf16 or fp16, plus a tenth for activations; tensors read in place from the file are paged
    // in on demand and not counted.
    const double need = (double(kept - kept_bf16) * 4.0 + double(kept_bf16) * 2.0) * 1.1;
    const double need_half = double(kept) * 2.0 * 1.1;
    const double avail = double(meminfo_bytes("MemAvailable"));
    out.push_back({"model", "weights", Status::ok,
                   count_str(params) + " parameters, " + gb(bytes) + " on disk" +
                       (store.sharded() ? " in " + std::to_string(files.size() - 1) + " shards" : ""),
                   ""});
    const std::string hash = models::weights_hash(d, files);
    out.push_back({"model", "sha256", Status::ok,
                   (files.size() == 1 ? files[0] : std::string("weights")) + " " + hash.substr(hash.find(':') + 1), ""});
    out.push_back({"model", "fits in memory (fp32)", need < avail ? Status::ok : Status::fail,
                   "needs about " + gb(need) + ", " + gb(avail) + " available",
                   "free memory, or run in bf16 (--precision bf16, about half)"});
    out.push_back({"model", "fits in memory (bf16)", need_half < avail ? Status::ok : Status::fail,
                   "needs about " + gb(need_half) + ", " + gb(avail) + " available",
                   "free memory, or use a machine with more"});
    if (family && has_config) {
      models::Normalization n;
      try {
        n = family->load_normalization(d, read_json_file((d / "config.json").string()), store, models::LoadOptions{});
      } catch (const Error& e) {
        // A checkpoint with several embodiments (GR00T) has statistics per embodiment: the server picks one.
        if (e.code() != ErrorCode::invalid_argument) throw;
        out.push_back({"model", "normalisation", Status::warn, e.what(),
                       "serve it with --embodiment-tag to check that embodiment's statistics"});
        return;
      }
      out.push_back({"model", "normalisation", n.warnings.empty() ? Status::ok : Status::warn,
                     n.warnings.empty() ? "statistics present for every normalised feature"
                                        : [&] {
                                            std::string all;
                                            for (const auto& w : n.warnings) all += (all.empty() ? "" : "; ") + w;
                                            return all;
                                          }(),
                     "ship the dataset statistics with the checkpoint (lerobot saves them with its processors)"});
    }
  } catch (const Error& e) {
    out.push_back({"model", "weights", Status::fail, e.what(), "re-download the checkpoint: the files are damaged"});
  }
}

struct DoctorArgs {
  std::string model;
  bool json = false;
};

int run_doctor(const DoctorArgs& a) {
  std::vector<Check> checks;
  cpu_checks(checks);
  memory_checks(checks);
  cuda_checks(checks);
  if (!a.model.empty()) model_checks(a.model, checks);
  bool failed = false;
  for (const auto& c : checks) failed |= c.status == Status::fail;
  if (a.json) {
    Json arr = Json::array();
    for (const auto& c : checks)
      arr.push_back({{"group", c.group}, {"check", c.name}, {"status", status_name(c.status)}, {"detail", c.detail},
                     {"remedy", c.status == Status::ok ? "" : c.remedy}});
    std::cout << Json{{"ok", !failed}, {"checks", arr}}.dump(2) << "\n";
  } else {
    std::string group;
    for (const auto& c : checks) {
      if (c.group != group) std::printf("%s\n", (group = c.group).c_str());
      std::printf("  %s %-22s %s\n", mark(c.status), c.name.c_str(), c.detail.c_str());
      if ((c.status == Status::fail || c.status == Status::warn) && !c.remedy.empty())
        std::printf("    -> %s\n", c.remedy.c_str());
    }
    std::printf("%s\n", failed ? "some checks failed" : "all required checks passed");
  }
  return failed ? kExitCheckFailed : kExitOk;
}

}  // namespace

Verb add_doctor(CLI::App& app) {
  auto args = std::make_shared<DoctorArgs>();
  CLI::App* sub = app.add_subcommand("doctor", "Check this machine (CPU features, memory, disk, CUDA) and a model directory");
  sub->add_option("model", args->model, "Checkpoint directory to check (optional)");
  sub->add_flag("--json", args->json, "Print JSON");
  return {sub, [args] { return run_doctor(*args); }};
}

}  // namespace tether::cli
