# Cross-build for aarch64 Linux (Jetson Orin / Thor) on a Debian amd64 machine with multiarch arm64 packages
# (crossbuild-essential-arm64, the libraries as `-dev:arm64`, qemu-user-static): scripts/check_arm64.sh sets it up.
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR aarch64)
set(CMAKE_LIBRARY_ARCHITECTURE aarch64-linux-gnu)

set(CMAKE_C_COMPILER aarch64-linux-gnu-gcc)
set(CMAKE_CXX_COMPILER aarch64-linux-gnu-g++)

# Multiarch, no separate sysroot: the arm64 libraries live in /usr/lib/aarch64-linux-gnu next to the host's, and
# with CMAKE_LIBRARY_ARCHITECTURE set find_library/find_package look there and never in x86_64-linux-gnu. The two
# -dev packages that cannot be installed next to their amd64 twins (libdnnl-dev, libonig-dev) are unpacked by
# scripts/check_arm64.sh into build/arm64-sysroot, which the arm64 preset puts on CMAKE_PREFIX_PATH (pkg-config
# searches its lib/aarch64-linux-gnu/pkgconfig too, below). Programs (python3, the code generators) are the host's.
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)

# pkg-config would otherwise answer with the host's .pc files (Debian ships no aarch64-linux-gnu-pkg-config).
# CMAKE_PREFIX_PATH's pkgconfig folders come first: FindPkgConfig adds them itself only when not cross-compiling.
# Not redone inside try_compile, which reads this file again without CMAKE_PREFIX_PATH and shares the environment.
get_property(_tether_in_try_compile GLOBAL PROPERTY IN_TRY_COMPILE)
if(NOT _tether_in_try_compile)
  set(_tether_pkg_config_dirs "")
  foreach(_tether_prefix IN LISTS CMAKE_PREFIX_PATH)
    string(APPEND _tether_pkg_config_dirs "${_tether_prefix}/lib/aarch64-linux-gnu/pkgconfig:")
  endforeach()
  set(ENV{PKG_CONFIG_LIBDIR} "${_tether_pkg_config_dirs}/usr/lib/aarch64-linux-gnu/pkgconfig:/usr/share/pkgconfig")
  set(ENV{PKG_CONFIG_PATH} "")
endif()

# Test binaries (gtest_discover_tests, ctest) run under user-mode emulation. The prefix is `/`, whose loader comes
# from libc6:arm64 (pulled in by the -dev:arm64 packages) and matches the libc in /lib/aarch64-linux-gnu that every
# library is found in; /usr/aarch64-linux-gnu (the cross toolchain's older glibc) would pair its loader with that
# newer libc, and threaded programs hang on it. QEMU_CPU in the environment picks the emulated CPU (the default, "max",
# has 512-bit SVE; scripts/check_arm64.sh runs the tests on an Orin-like and a Thor-like CPU).
find_program(TETHER_QEMU_AARCH64 qemu-aarch64-static qemu-aarch64)
if(TETHER_QEMU_AARCH64)
  set(CMAKE_CROSSCOMPILING_EMULATOR "${TETHER_QEMU_AARCH64};-L;/")
endif()
