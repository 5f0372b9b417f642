#include "piezo_compensation/models/registry.h"

#include <map>
#include <stdexcept>

namespace piezo::models {

namespace {
std::map<std::string, ModelKind>& kinds() {
  static std::map<std::string, ModelKind> k;
  return k;
}
}  // namespace

void register_model_kind(ModelKind kind) {
  const std::string name = kind.name;
  kinds()[name] = std::move(kind);
}

const ModelKind& model_kind(const std::string& name) {
  auto it = kinds().find(name);
  if (it == kinds().end()) {
    std::string known;
    for (const auto& [n, k] : kinds()) known += (known.empty() ? "" : ", ") + n;
    throw std::runtime_error("unknown model kind '" + name + "' (known: " + (known.empty() ? "none" : known) + ")");
  }
  return it->second;
}

std::vector<std::string> model_kind_names() {
  std::vector<std::string> names;
  for (const auto& [n, k] : kinds()) names.push_back(n);
  return names;
}

}  // namespace piezo::models
