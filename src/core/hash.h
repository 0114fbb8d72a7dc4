// Content digests: sha256 (model hashes, LFS ETags) and git blob sha1, through OpenSSL.
#pragma once

#include <string>

namespace tether {

// Lower-case hex digests of a whole file; throw Error(io) when it cannot be read.
std::string sha256_file_hex(const std::string& path);
// sha1 of "blob <size>\0<content>": the id git gives a file's content (the hub's ETag for files kept in git).
std::string git_blob_sha1_file_hex(const std::string& path);

std::string sha256_hex(const std::string& data);
std::string git_blob_sha1_hex(const std::string& data);

bool is_sha256_hex(const std::string& s);  // 64 lower-case hex digits
bool is_sha1_hex(const std::string& s);    // 40 lower-case hex digits (also a commit hash)

}  // namespace tether
