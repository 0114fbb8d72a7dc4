// Machine probes (CPU, memory, CUDA driver and libraries through dlopen) and the choices `tether go` makes from them.
#include "cli/hardware.h"

#include "backend/backend.h"
#include "backend/cpu/cpu_features.h"

#include <dlfcn.h>
#include <unistd.h>

#include <cstdio>
#include <fstream>

namespace tether::cli {

namespace {

// Opens the first library of `names` that loads; returns its handle and the name used. Handles stay open for the
// process: a driver that was initialised must not be unloaded under its own threads.
std::pair<void*, std::string> open_any(std::initializer_list<const char*> names) {
  for (const char* n : names)
    if (void* h = dlopen(n, RTLD_NOW | RTLD_LOCAL)) return {h, n};
  return {nullptr, ""};
}

template <typename Fn>
Fn symbol(void* lib, const char* name) {
  return reinterpret_cast<Fn>(dlsym(lib, name));
}

std::string gb(double bytes) {
  char buf[32];
  if (bytes < 1e9) std::snprintf(buf, sizeof buf, "%.1f MB", bytes / 1e6);
  else std::snprintf(buf, sizeof buf, "%.1f GB", bytes / 1e9);
  return buf;
}

}  // namespace

GpuProbe probe_gpus() {
  GpuProbe p;
  auto [cuda, name] = open_any({"libcuda.so.1", "libcuda.so"});
  if (!cuda) return p;
  p.driver_library = name;
  using InitFn = int (*)(unsigned);
  using IntOutFn = int (*)(int*);  // cuDriverGetVersion, cuDeviceGetCount
  using DeviceFn = int (*)(int*, int);
  using AttrFn = int (*)(int*, int, int);
  using NameFn = int (*)(char*, int, int);
  using MemFn = int (*)(std::size_t*, int);
  auto init = symbol<InitFn>(cuda, "cuInit");
  auto version = symbol<IntOutFn>(cuda, "cuDriverGetVersion");
  auto count = symbol<IntOutFn>(cuda, "cuDeviceGetCount");
  auto device = symbol<DeviceFn>(cuda, "cuDeviceGet");
  auto attr = symbol<AttrFn>(cuda, "cuDeviceGetAttribute");
  auto dev_name = symbol<NameFn>(cuda, "cuDeviceGetName");
  auto total_mem = symbol<MemFn>(cuda, "cuDeviceTotalMem_v2");
  // Free memory needs a context: the device's primary one, retained and released around the query.
  using RetainFn = int (*)(void**, int);
  using ReleaseFn = int (*)(int);
  using SetCurrentFn = int (*)(void*);
  using MemInfoFn = int (*)(std::size_t*, std::size_t*);
  auto retain = symbol<RetainFn>(cuda, "cuDevicePrimaryCtxRetain");
  auto release = symbol<ReleaseFn>(cuda, "cuDevicePrimaryCtxRelease_v2");
  auto set_current = symbol<SetCurrentFn>(cuda, "cuCtxSetCurrent");
  auto mem_info = symbol<MemInfoFn>(cuda, "cuMemGetInfo_v2");
  if (!init || !version || init(0) != 0 || version(&p.driver_version) != 0) return p;
  p.driver_ok = true;
  int n = 0;
  if (!count || !device || !attr || !dev_name || count(&n) != 0) return p;
  for (int i = 0; i < n; ++i) {
    int dev = 0;
    if (device(&dev, i) != 0) continue;
    GpuDevice g;
    char buf[256] = {0};
    dev_name(buf, sizeof buf, dev);
    g.name = buf;
    attr(&g.cc_major, 75, dev);  // CU_DEVICE_ATTRIBUTE_COMPUTE_CAPABILITY_MAJOR
    attr(&g.cc_minor, 76, dev);  // ..._MINOR
    std::size_t bytes = 0;
    if (total_mem && total_mem(&bytes, dev) == 0) g.memory_bytes = int64_t(bytes);
    if (void* ctx = nullptr; retain && release && set_current && mem_info && retain(&ctx, dev) == 0) {
      std::size_t free_now = 0, total = 0;
      if (set_current(ctx) == 0 && mem_info(&free_now, &total) == 0) g.free_bytes = int64_t(free_now);
      set_current(nullptr);
      release(dev);
    }
    p.devices.push_back(std::move(g));
  }
  return p;
}

CudaLibraries probe_cuda_libraries() {
  CudaLibraries out;
  if (auto [rt, name] = open_any({"libcudart.so.13", "libcudart.so.12", "libcudart.so"}); rt) {
    out.runtime.file = name;
    auto f = symbol<int (*)(int*)>(rt, "cudaRuntimeGetVersion");
    if (int v = 0; f && f(&v) == 0 && v) out.runtime.version = cuda_version_str(v);
  }
  if (auto [blas, name] = open_any({"libcublas.so.13", "libcublas.so.12", "libcublas.so"}); blas) {
    out.cublas.file = name;
    auto f = symbol<int (*)(int, int*)>(blas, "cublasGetProperty");  // 0, 1, 2: major, minor, patch
    if (int ma = 0, mi = 0, pa = 0; f && f(0, &ma) == 0 && f(1, &mi) == 0 && f(2, &pa) == 0)
      out.cublas.version = std::to_string(ma) + "." + std::to_string(mi) + "." + std::to_string(pa);
  }
  if (auto [dnn, name] = open_any({"libcudnn.so.9", "libcudnn.so.8", "libcudnn.so"}); dnn) {
    out.cudnn.file = name;
    if (auto f = symbol<std::size_t (*)()>(dnn, "cudnnGetVersion")) out.cudnn.version = std::to_string(f());
  }
  return out;
}

std::string cpu_model() {
  std::ifstream in("/proc/cpuinfo");
  std::string line;
  while (std::getline(in, line))
    if (line.rfind("model name", 0) == 0) return line.substr(line.find(':') + 2);
  // aarch64's /proc/cpuinfo has no model name; the device tree names the board (a Jetson's, for one).
  std::ifstream board("/proc/device-tree/model");
  if (std::getline(board, line, '\0') && !line.empty()) return line;
  return "unknown CPU";
}

int64_t meminfo_bytes(const std::string& key) {
  std::ifstream in("/proc/meminfo");
  std::string name, unit;
  int64_t value = 0;
  while (in >> name >> value >> unit)
    if (name == key + ":") return value * 1024;
  return -1;
}

double memory_needed_bytes(int64_t parameters, const std::string& precision) {
  const double bytes_per = precision == "fp32" ? 4.0 : 2.0;
  return double(parameters) * bytes_per * 1.25;  // weights plus activations, caches and the runtime
}

MachineProbe probe_machine() {
  MachineProbe m;
  m.cpu = cpu_model();
  m.cores = int(sysconf(_SC_NPROCESSORS_ONLN));
  m.memory_total = meminfo_bytes("MemTotal");
  m.memory_available = meminfo_bytes("MemAvailable");
  m.native_bf16 = cpu::cpu_paths().native_bf16;
  m.bf16_widened_reason = cpu::bf16_widened_reason();
  m.isa = cpu::isa_name(cpu::cpu_paths().effective);
  m.gpu = probe_gpus();
  return m;
}

bool supported_compute_capability(int major, int minor) {
  const int cc = major * 10 + minor;
  for (int s : {80, 86, 87, 89, 90, 100, 103, 110, 120, 121})
    if (cc == s) return true;
  return false;
}

std::string cuda_version_str(int version) {
  return std::to_string(version / 1000) + "." + std::to_string((version % 1000) / 10);
}

std::string gpu_summary(const GpuProbe& p) {
  if (p.driver_library.empty()) return "GPU: none found (no NVIDIA driver: libcuda.so.1 not found); serving on CPU";
  if (!p.driver_ok) return "GPU: none found (" + p.driver_library + " loaded but cuInit failed); serving on CPU";
  if (p.devices.empty())
    return "GPU: none found (CUDA driver " + cuda_version_str(p.driver_version) + ", no devices); serving on CPU";
  std::string s = "GPU: ";
  for (std::size_t i = 0; i < p.devices.size(); ++i) {
    const GpuDevice& g = p.devices[i];
    char mem[32] = "";
    if (g.memory_bytes > 0) std::snprintf(mem, sizeof mem, ", %.0f GiB", double(g.memory_bytes) / double(1ull << 30));
    s += (i ? ", " : "") + g.name + " (compute " + std::to_string(g.cc_major) + "." + std::to_string(g.cc_minor) + mem +
         (supported_compute_capability(g.cc_major, g.cc_minor) ? "" : ", below the supported 8.0") + ")";
  }
  std::string why;
  if (backend::backend_usable("cuda", &why)) return s + " \u2014 the CUDA backend serves on it";
  return s + " \u2014 " + why + "; serving on CPU";
}

std::string cpu_summary(const MachineProbe& m) {
  std::string s = "CPU: " + m.cpu + ", " + std::to_string(m.cores) + " cores; memory: ";
  if (m.memory_available < 0) return s + "unknown (no /proc/meminfo)";
  return s + gb(double(m.memory_available)) + " available of " + gb(double(m.memory_total));
}

PrecisionChoice choose_precision(const MachineProbe& m, const std::string& model_id, std::optional<int64_t> parameters,
                                 const std::string& asked) {
  if (!asked.empty()) return {asked, "precision " + asked + ": asked with --precision"};
  if (m.native_bf16)
    return {"bf16", "precision bf16: this CPU (" + m.isa +
                        ") runs bf16 GEMMs natively, faster than fp32; its error against fp32 is in the export's "
                        "VERIFICATION.md (--precision fp32 for the reference)"};
  const std::string slow = "bf16 would be no faster here (" + m.isa + ": " + m.bf16_widened_reason + ")";
  if (!parameters) return {"fp32", "precision fp32 (the reference): " + model_id + " has no parameter count, memory not checked"};
  if (m.memory_available <= 0) return {"fp32", "precision fp32 (the reference): available memory unknown"};
  const double need = memory_needed_bytes(*parameters, "fp32");
  char avail[32];
  std::snprintf(avail, sizeof avail, "%.1f GB", double(m.memory_available) / 1e9);
  // Leave a fifth of the memory to the OS and the robot stack.
  if (need > 0.8 * double(m.memory_available))
    return {"bf16", model_id + " does not fit in fp32 here (" + avail +
                        " available): using bf16 weights, widened to fp32 in the kernel (half the memory)"};
  return {"fp32", "precision fp32 (the reference): " + model_id + " needs about " + gb(need) + ", " + avail +
                      " available; " + slow};
}

}  // namespace tether::cli
