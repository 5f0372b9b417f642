// `--allow-training-rows` and its check, one for the tools that score a model on data (eval, track, residual):
// rows the model file records as its training rows are refused with one line naming them, or scored with a warning.
#pragma once

#include <iostream>
#include <string>

#include "args.h"
#include "piezo_compensation/models/model_file.h"

namespace piezo::cli {

inline Args& allow_training_rows_option(Args& args) {
  return args.option("allow-training-rows", "", "score rows the model was trained on (refused otherwise: a figure on them\n"
                     "says nothing about new data)");
}

// `what`: how the data are named in the message ("" or e.g. "TEST "); `verb`: what the tool does with the rows.
inline void check_training_rows(const Args& args, const std::string& command, const models::ModelMeta& meta,
                                const io::Dataset& data, const std::string& axis, const std::string& model_path,
                                const std::string& what = "", const std::string& verb = "scores") {
  const std::string overlap = models::training_overlap(meta, data, axis, model_path);
  if (overlap.empty()) return;
  if (!args.flag("allow-training-rows"))
    throw UsageError(command + ": " + what + overlap + "; --allow-training-rows " + verb + " them anyway");
  std::cerr << "warning: " << what << overlap << " (" << verb << " them: --allow-training-rows)\n";
}

}  // namespace piezo::cli
