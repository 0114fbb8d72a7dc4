# The optional CUDA backend: found, checked and configured here, so the rest of the build only reads
# TETHER_CUDA_ENABLED. Without nvcc (or with -DTETHER_CUDA=OFF) nothing here changes the CPU build.
#
# GPU targets (TETHER_CUDA_ARCHS, overridable): machine code for the GPUs robots and labs run, plus PTX of the newest
# listed generation so that later parts can compile it at load time:
#   86 RTX 30 / A10, 87 Jetson Orin, 89 RTX 40 / L4 / L40, 90a H100 / H200 (Hopper-only instructions),
#   110 Jetson Thor (CUDA 13 and newer), 120 RTX 50 / RTX PRO Blackwell (CUDA 12.8 and newer).
option(TETHER_CUDA "Build the CUDA backend when nvcc (CUDA 12.6 or newer) is found" ON)
set(TETHER_CUDA_ENABLED OFF)
set(TETHER_CUDA_MINIMUM 12.6)

if(TETHER_CUDA AND CMAKE_CROSSCOMPILING)
  # A cross build would need the target's CUDA runtime and cuBLASLt to link against; Debian ships none for aarch64
  # (see docs/setup.md, "GPU").
  message(STATUS "CUDA backend: not built in a cross build (no CUDA libraries for the target)")
elseif(TETHER_CUDA)
  if(NOT CMAKE_CUDA_COMPILER AND NOT DEFINED ENV{CUDACXX})
    find_program(TETHER_NVCC nvcc HINTS /usr/local/cuda/bin)
    if(TETHER_NVCC)
      set(ENV{CUDACXX} "${TETHER_NVCC}")
    endif()
  endif()
  include(CheckLanguage)
  check_language(CUDA)
  if(CMAKE_CUDA_COMPILER)
    # Targets are given as -gencode pairs below; CMake's own architecture handling stays out of the way.
    set(CMAKE_CUDA_ARCHITECTURES OFF)
    enable_language(CUDA)
    find_package(CUDAToolkit)
    if(CMAKE_CUDA_COMPILER_VERSION VERSION_LESS TETHER_CUDA_MINIMUM)
      message(STATUS "CUDA backend: nvcc ${CMAKE_CUDA_COMPILER_VERSION} is older than ${TETHER_CUDA_MINIMUM}; not built")
    elseif(NOT TARGET CUDA::cublasLt OR NOT TARGET CUDA::cudart_static)
      message(STATUS "CUDA backend: cuBLASLt or the CUDA runtime was not found; not built")
    else()
      set(TETHER_CUDA_ENABLED ON)
    endif()
  else()
    message(STATUS "CUDA backend: no nvcc found; not built")
  endif()
endif()

if(TETHER_CUDA_ENABLED)
  set(_archs 86 87 89 90a)
  if(CMAKE_CUDA_COMPILER_VERSION VERSION_GREATER_EQUAL 13.0)
    list(APPEND _archs 110)
  endif()
  if(CMAKE_CUDA_COMPILER_VERSION VERSION_GREATER_EQUAL 12.8)
    list(APPEND _archs 120)
  endif()
  set(TETHER_CUDA_ARCHS "${_archs}" CACHE STRING "GPU architectures the CUDA backend is built for (machine code)")
  list(GET TETHER_CUDA_ARCHS -1 _newest)
  string(REGEX REPLACE "a$" "" _newest_ptx "${_newest}")
  set(_gencode "")
  set(_names "")
  foreach(arch IN LISTS TETHER_CUDA_ARCHS)
    string(APPEND _gencode " -gencode=arch=compute_${arch},code=sm_${arch}")
    list(APPEND _names "sm_${arch}")
  endforeach()
  string(APPEND _gencode " -gencode=arch=compute_${_newest_ptx},code=compute_${_newest_ptx}")
  list(JOIN _names ", " _names)
  set(TETHER_CUDA_TARGETS "${_names} and PTX compute_${_newest_ptx}")
  set(CMAKE_CUDA_FLAGS "${CMAKE_CUDA_FLAGS}${_gencode}")
  set(CMAKE_CUDA_STANDARD 17)
  set(CMAKE_CUDA_STANDARD_REQUIRED ON)
  # ptxas warns about register spills in every kernel (and, for the hot kernels, about any local memory:
  # src/backend/CMakeLists.txt); with warnings as errors (CI) either fails the build.
  string(APPEND CMAKE_CUDA_FLAGS " -Xptxas=-warn-spills -Xcompiler=-Wall,-Wextra")
  if(TETHER_WERROR)
    string(APPEND CMAKE_CUDA_FLAGS " -Werror=all-warnings -Xptxas=-Werror -Xcompiler=-Werror")
  endif()
  message(STATUS "CUDA backend: nvcc ${CMAKE_CUDA_COMPILER_VERSION}, targets ${TETHER_CUDA_TARGETS}")
endif()
# Read by scripts/check_cuda_build.sh.
set(TETHER_HAVE_CUDA_BUILD ${TETHER_CUDA_ENABLED} CACHE INTERNAL "")
set(TETHER_CUDA_TARGETS_TEXT "${TETHER_CUDA_TARGETS}" CACHE INTERNAL "")
