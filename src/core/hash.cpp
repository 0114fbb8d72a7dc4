// sha256 and git blob sha1 through OpenSSL's EVP interface; files are streamed in 1 MiB pieces.
#include "core/hash.h"

#include <openssl/evp.h>

#include <cstdio>
#include <filesystem>
#include <memory>
#include <vector>

#include "core/error.h"

namespace tether {
namespace {

struct MdCtxDeleter {
  void operator()(EVP_MD_CTX* c) const { EVP_MD_CTX_free(c); }
};
using MdCtx = std::unique_ptr<EVP_MD_CTX, MdCtxDeleter>;

MdCtx new_ctx(const EVP_MD* md) {
  MdCtx ctx(EVP_MD_CTX_new());
  if (!ctx || EVP_DigestInit_ex(ctx.get(), md, nullptr) != 1)
    throw Error(ErrorCode::internal, "hash: EVP_DigestInit_ex failed");
  return ctx;
}

std::string finish_hex(EVP_MD_CTX* ctx) {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int n = 0;
  if (EVP_DigestFinal_ex(ctx, digest, &n) != 1)
    throw Error(ErrorCode::internal, "hash: EVP_DigestFinal_ex failed");
  static const char* digits = "0123456789abcdef";
  std::string out(2 * n, '0');
  for (unsigned int i = 0; i < n; ++i) {
    out[2 * i] = digits[digest[i] >> 4];
    out[2 * i + 1] = digits[digest[i] & 15];
  }
  return out;
}

void update_from_file(EVP_MD_CTX* ctx, const std::string& path) {
  std::unique_ptr<FILE, int (*)(FILE*)> f(std::fopen(path.c_str(), "rb"), &std::fclose);
  if (!f) throw Error(ErrorCode::io, path + ": cannot open for hashing");
  std::vector<unsigned char> buf(1 << 20);
  size_t n;
  while ((n = std::fread(buf.data(), 1, buf.size(), f.get())) > 0)
    EVP_DigestUpdate(ctx, buf.data(), n);
  if (std::ferror(f.get()))
    throw Error(ErrorCode::io, path + ": read error while hashing");
}

std::string git_header(uint64_t size) {
  return "blob " + std::to_string(size) + std::string(1, '\0');
}

bool is_lower_hex(const std::string& s, size_t len) {
  if (s.size() != len) return false;
  for (char c : s)
    if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
  return true;
}

}  // namespace

std::string sha256_file_hex(const std::string& path) {
  auto ctx = new_ctx(EVP_sha256());
  update_from_file(ctx.get(), path);
  return finish_hex(ctx.get());
}

std::string git_blob_sha1_file_hex(const std::string& path) {
  std::error_code ec;
  auto size = std::filesystem::file_size(path, ec);
  if (ec)
    throw Error(ErrorCode::io, path + ": cannot stat for hashing (" + ec.message() + ")");
  auto ctx = new_ctx(EVP_sha1());
  std::string header = git_header(size);
  EVP_DigestUpdate(ctx.get(), header.data(), header.size());
  update_from_file(ctx.get(), path);
  return finish_hex(ctx.get());
}

std::string sha256_hex(const std::string& data) {
  auto ctx = new_ctx(EVP_sha256());
  EVP_DigestUpdate(ctx.get(), data.data(), data.size());
  return finish_hex(ctx.get());
}

std::string git_blob_sha1_hex(const std::string& data) {
  auto ctx = new_ctx(EVP_sha1());
  std::string header = git_header(data.size());
  EVP_DigestUpdate(ctx.get(), header.data(), header.size());
  EVP_DigestUpdate(ctx.get(), data.data(), data.size());
  return finish_hex(ctx.get());
}

bool is_sha256_hex(const std::string& s) { return is_lower_hex(s, 64); }
bool is_sha1_hex(const std::string& s) { return is_lower_hex(s, 40); }

}  // namespace tether
