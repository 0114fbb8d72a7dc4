// What this machine offers a policy: CPU, memory, and NVIDIA GPUs found through the CUDA driver (opened with dlopen,
// so the binary runs where CUDA is absent). Shared by `tether doctor` and `tether go`; the choices made from a probe
// are plain functions of it, so they are tested with made-up machines.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

namespace tether::cli {

struct GpuDevice {
  std::string name;
  int cc_major = 0, cc_minor = 0;  // compute capability
  int64_t memory_bytes = 0;
  int64_t free_bytes = -1;  // -1: not read (no context could be made)
};

struct GpuProbe {
  std::string driver_library;  // the libcuda that loaded; empty when there is no NVIDIA driver
  bool driver_ok = false;      // cuInit and cuDriverGetVersion succeeded
  int driver_version = 0;      // CUDA driver API version, e.g. 12040
  std::vector<GpuDevice> devices;
};

// A CUDA library opened with dlopen: the soname that loaded (empty when none did) and the version it reports
// (empty when it reports none).
struct CudaLibrary {
  std::string file, version;
};
struct CudaLibraries {
  CudaLibrary runtime, cublas, cudnn;
};

struct MachineProbe {
  std::string cpu;  // model name from /proc/cpuinfo
  int cores = 0;
  int64_t memory_total = -1, memory_available = -1;  // bytes; -1 when /proc/meminfo lacks the field
  // bf16 GEMMs run on the CPU's bf16 instructions (cpu::cpu_paths(), under TETHER_MAX_CPU_ISA); without them bf16
  // weights are widened to fp32 in the kernel: half the memory, no faster than fp32.
  bool native_bf16 = false;
  std::string bf16_widened_reason = "this CPU has no bf16 instructions";  // why not native (cpu::bf16_widened_reason())
  std::string isa;  // the dispatch level, e.g. "avx2", "avx512_bf16"
  GpuProbe gpu;
};

GpuProbe probe_gpus();
CudaLibraries probe_cuda_libraries();
MachineProbe probe_machine();

std::string cpu_model();
// A /proc/meminfo field in bytes ("MemAvailable", "MemTotal"); -1 when absent.
int64_t meminfo_bytes(const std::string& key);
// Approximate memory to run `parameters` weights at `precision` ("fp32", "bf16", "fp16"), activations included.
double memory_needed_bytes(int64_t parameters, const std::string& precision);

// Compute capabilities the CUDA kernels are written for (Ampere and newer).
bool supported_compute_capability(int major, int minor);
// 12040 -> "12.4".
std::string cuda_version_str(int version);

// The line `tether go` prints about GPUs: "GPU: none found (...)" or "GPU: NVIDIA H100 80GB HBM3 (compute 9.0,
// 80 GiB) — the CUDA backend is not part of this build; serving on CPU".
std::string gpu_summary(const GpuProbe& probe);
// "CPU: <model>, 16 cores; memory: 12.3 GB available of 16.0 GB".
std::string cpu_summary(const MachineProbe& probe);

struct PrecisionChoice {
  std::string precision, reason;  // reason: one line saying what decided it
};
// `asked` when given. Otherwise bf16 where the CPU has bf16 instructions (faster than fp32); elsewhere fp32 (the
// reference), and bf16 (widened weights, half the memory) only when fp32 would not fit 80% of the available memory.
PrecisionChoice choose_precision(const MachineProbe& machine, const std::string& model_id,
                                 std::optional<int64_t> parameters, const std::string& asked);

}  // namespace tether::cli
