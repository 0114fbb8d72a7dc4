// The CUDA backend (compiled when CMake finds nvcc): device memory from a cached pool, linear layers through cuBLASLt
// (fp32 without TF32 as the parity mode; bf16 and fp16 weights on tensor cores with fp32 accumulation), and the
// backend's own kernels for the rest (kernels.cu, attention.cu).
#pragma once

#include <memory>
#include <string>

#include "backend/backend.h"

namespace tether::backend {

// Throws Error(unavailable) with a one-line reason when no usable device is present.
std::shared_ptr<Backend> make_cuda_backend();
// Whether a device is present that this build has code for; `why` gets the reason when not.
bool cuda_usable(std::string* why);

}  // namespace tether::backend
