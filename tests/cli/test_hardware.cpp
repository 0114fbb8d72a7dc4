// The machine probe's reports and the precision `tether go` picks, for made-up machines (GPU or none, little or
// plenty of memory), and the real probe on this machine.
#include <dlfcn.h>
#include <gtest/gtest.h>

#include "backend/backend.h"

#include "cli/hardware.h"

using namespace tether::cli;

namespace {

GpuProbe driver_with(std::vector<GpuDevice> devices) {
  GpuProbe p;
  p.driver_library = "libcuda.so.1";
  p.driver_ok = true;
  p.driver_version = 12040;
  p.devices = std::move(devices);
  return p;
}

MachineProbe machine_with(int64_t available_bytes) {
  MachineProbe m;
  m.cpu = "Test CPU";
  m.cores = 8;
  m.memory_total = 2 * available_bytes;
  m.memory_available = available_bytes;
  m.isa = "avx2";
  return m;
}

}  // namespace

TEST(HardwareProbe, NoGpuSaysWhy) {
  EXPECT_EQ(gpu_summary(GpuProbe{}), "GPU: none found (no NVIDIA driver: libcuda.so.1 not found); serving on CPU");
  GpuProbe broken;
  broken.driver_library = "libcuda.so.1";
  EXPECT_EQ(gpu_summary(broken), "GPU: none found (libcuda.so.1 loaded but cuInit failed); serving on CPU");
  EXPECT_EQ(gpu_summary(driver_with({})), "GPU: none found (CUDA driver 12.4, no devices); serving on CPU");
}

// The summary ends with what this binary does with the GPU: the CUDA backend's own verdict (backend_usable), on a
// machine where the probe saw a GPU (faked here) but the backend cannot use it.
TEST(HardwareProbe, GpuFoundButServedOnCpu) {
  std::string why;
  if (tether::backend::backend_usable("cuda", &why)) GTEST_SKIP() << "skipped: a CUDA device is usable here";
  const GpuDevice h100{"NVIDIA H100 80GB HBM3", 9, 0, int64_t(80) << 30};
  EXPECT_EQ(gpu_summary(driver_with({h100})),
            "GPU: NVIDIA H100 80GB HBM3 (compute 9.0, 80 GiB) \u2014 " + why + "; serving on CPU");
  const GpuDevice t4{"Tesla T4", 7, 5, int64_t(15) << 30};
  EXPECT_EQ(gpu_summary(driver_with({h100, t4})),
            "GPU: NVIDIA H100 80GB HBM3 (compute 9.0, 80 GiB), Tesla T4 (compute 7.5, 15 GiB, below the supported 8.0) "
            "\u2014 " + why + "; serving on CPU");
  const GpuDevice no_memory{"Orin", 8, 7, 0};  // cuDeviceTotalMem missing: no size rather than "0 GiB"
  EXPECT_EQ(gpu_summary(driver_with({no_memory})).rfind("GPU: Orin (compute 8.7) ", 0), 0u);
}

TEST(HardwareProbe, ComputeCapabilityAndVersions) {
  EXPECT_TRUE(supported_compute_capability(8, 0));
  EXPECT_TRUE(supported_compute_capability(12, 1));
  EXPECT_FALSE(supported_compute_capability(7, 5));
  EXPECT_EQ(cuda_version_str(12040), "12.4");
  EXPECT_EQ(cuda_version_str(13000), "13.0");
}

TEST(HardwareProbe, CpuSummary) {
  EXPECT_EQ(cpu_summary(machine_with(int64_t(12'300'000'000))),
            "CPU: Test CPU, 8 cores; memory: 12.3 GB available of 24.6 GB");
  MachineProbe no_meminfo = machine_with(1);
  no_meminfo.memory_available = -1;
  EXPECT_EQ(cpu_summary(no_meminfo), "CPU: Test CPU, 8 cores; memory: unknown (no /proc/meminfo)");
}

TEST(HardwareProbe, PrecisionIsFp32UnlessAskedOrTooBig) {
  const MachineProbe m = machine_with(int64_t(16'000'000'000));
  PrecisionChoice c = choose_precision(m, "tiny", int64_t(1'000'000), "");
  EXPECT_EQ(c.precision, "fp32");
  EXPECT_EQ(c.reason, "precision fp32 (the reference): tiny needs about 5.0 MB, 16.0 GB available; bf16 would be "
                      "no faster here (avx2: this CPU has no bf16 instructions)");
  // 3.3B parameters need ~16.5 GB in fp32: more than 80% of 16 GB.
  c = choose_precision(m, "pi0", int64_t(3'300'000'000), "");
  EXPECT_EQ(c.precision, "bf16");
  EXPECT_EQ(c.reason, "pi0 does not fit in fp32 here (16.0 GB available): using bf16 weights, widened to fp32 in the "
                      "kernel (half the memory)");
  c = choose_precision(m, "pi0", int64_t(3'300'000'000), "fp16");
  EXPECT_EQ(c.precision, "fp16");
  EXPECT_EQ(c.reason, "precision fp16: asked with --precision");
  c = choose_precision(m, "x", std::nullopt, "");
  EXPECT_EQ(c.precision, "fp32");
  EXPECT_NE(c.reason.find("no parameter count"), std::string::npos);
  c = choose_precision(machine_with(-1), "x", int64_t(1'000'000'000'000), "");
  EXPECT_EQ(c.precision, "fp32");
  EXPECT_NE(c.reason.find("available memory unknown"), std::string::npos);
}

TEST(HardwareProbe, NativeBf16IsPickedForSpeed) {
  MachineProbe m = machine_with(int64_t(16'000'000'000));
  m.native_bf16 = true;
  m.isa = "avx512_bf16";
  const PrecisionChoice c = choose_precision(m, "tiny", int64_t(1'000'000), "");
  EXPECT_EQ(c.precision, "bf16");
  EXPECT_EQ(c.reason.rfind("precision bf16: this CPU (avx512_bf16) runs bf16 GEMMs natively", 0), 0u) << c.reason;
  EXPECT_EQ(choose_precision(m, "tiny", int64_t(1'000'000), "fp32").precision, "fp32");
}

TEST(HardwareProbe, RealProbeOfThisMachine) {
  const MachineProbe m = probe_machine();
  EXPECT_GT(m.cores, 0);
  EXPECT_GT(m.memory_available, 0);
  EXPECT_FALSE(m.cpu.empty());
  // Without a loadable driver the probe must say so, not invent a device.
  if (void* h = dlopen("libcuda.so.1", RTLD_NOW | RTLD_LOCAL); !h) {
    EXPECT_TRUE(m.gpu.driver_library.empty());
    EXPECT_TRUE(m.gpu.devices.empty());
    EXPECT_EQ(gpu_summary(m.gpu).rfind("GPU: none found", 0), 0u);
  }
}
