// Refuses to start on an x86-64 CPU older than the build's baseline (x86-64-v3: AVX2, FMA, F16C) with a message,
// instead of dying on the first illegal instruction. Compiled for plain x86-64 and run before any other
// constructor, since those may already use AVX2.
#if defined(__x86_64__)
#include <unistd.h>

namespace {

__attribute__((constructor(101))) void require_x86_64_v3() {
  __builtin_cpu_init();
  if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") && __builtin_cpu_supports("f16c")) return;
  static const char msg[] =
      "error: this CPU lacks AVX2/FMA/F16C; Tether needs an x86-64-v3 processor (Intel Haswell, AMD Zen or newer)\n";
  (void)!write(2, msg, sizeof msg - 1);
  _exit(2);
}

}  // namespace
#endif
