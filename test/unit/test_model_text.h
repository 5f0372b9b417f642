// Model-file text round trips for the model tests: the text of a model, a model from text, and the one error a
// loader gives when a piece of the text is replaced.
#pragma once

#include <gtest/gtest.h>

#include <string>

#include "piezo_compensation/models/model_file.h"

namespace piezo {

namespace {

// Model-file text of m, and the error loading it with `from` replaced by `to` ("loaded" if none).
std::string model_file_text(const models::Model& m) {
  YAML::Emitter em;
  em << models::model_to_file_yaml(m);
  return em.c_str();
}
models::ModelPtr model_from_text(const std::string& t) { return models::model_from_file_yaml(YAML::Load(t), "test"); }
std::string load_error_after(std::string text, const std::string& from, const std::string& to) {
  const auto at = text.find(from);
  EXPECT_NE(at, std::string::npos) << from;
  if (at == std::string::npos) return std::string();
  text.replace(at, from.size(), to);
  try {
    model_from_text(text);
  } catch (const std::exception& e) {
    return std::string(e.what());
  }
  return std::string("loaded");
}

}  // namespace

}  // namespace piezo
