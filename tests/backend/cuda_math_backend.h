// The CUDA backend's kernels run on the host: each operation loops over the elements the way its kernel's threads
// do and calls the same per-element functions (src/backend/cuda/element_math.h), attention included with its key
// tiles and running softmax. test_backend_ops runs it against the float64 references on every machine, so a device
// run has only the kernels' indexing and synchronisation left to prove.
#pragma once

#include <memory>

#include "backend/backend.h"

namespace tether::backend {

std::shared_ptr<Backend> make_cuda_math_on_host_backend();

}  // namespace tether::backend
