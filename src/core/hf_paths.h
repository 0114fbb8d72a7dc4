// Where the Hugging Face cache lives: resolved here once, for the hub client, the backbone lookup and the doctor,
// in the order huggingface_hub's constants.py uses.
#pragma once

#include <string>

namespace tether {

// $HF_HOME, else $XDG_CACHE_HOME/huggingface, else ~/.cache/huggingface.
std::string hf_home();

// The hub cache root: $HF_HUB_CACHE, else the legacy $HUGGINGFACE_HUB_CACHE, else hf_home()/hub.
// As huggingface_hub does, "~" and "$VAR" / "${VAR}" in the chosen value are expanded (os.path.expanduser, then
// os.path.expandvars; unknown variables stay as written). Unlike os.getenv, a variable set to "" counts as unset.
std::string hf_hub_cache();

// os.path.expanduser then os.path.expandvars on one path (exposed for tests).
std::string expand_user_and_vars(const std::string& path);

}  // namespace tether
