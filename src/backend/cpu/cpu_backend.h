// The CPU backend behind the backend interface (backend/backend.h).
#pragma once

#include <memory>

#include "backend/backend.h"

namespace tether::backend {

std::shared_ptr<Backend> make_cpu_backend();

}  // namespace tether::backend
