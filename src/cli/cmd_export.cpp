// `piezo export`: a model file as a dependency-free C99 header for the manipulator's own controller.
#include <cctype>
#include <filesystem>
#include <fstream>
#include <iostream>

#include "args.h"
#include "command.h"
#include "piezo_compensation/models/c_export.h"
#include "piezo_compensation/models/model_file.h"

namespace piezo::cli {
namespace {

int run(int argc, char** argv) {
  Args args("export", "Write a model file as a C99 header: state struct, <prefix>_init, _predict, _commit, _step\n"
                      "and, where the model has a closed form, _inverse. Kinds: linear, pi, pi_creep_*, preisach*.");
  args.required("model", "FILE.yaml", "model file")
      .required("c-header", "FILE.h", "header to write")
      .option("prefix", "NAME", "C identifier prefix (default: from the header file name)");
  if (!args.parse(argc, argv)) return 0;
  const models::ModelPtr m = models::load_model(args.str("model"));
  std::string prefix = args.str("prefix");
  if (prefix.empty()) {
    prefix = std::filesystem::path(args.str("c-header")).stem().string();
    for (char& c : prefix)
      if (!std::isalnum(static_cast<unsigned char>(c))) c = '_';
    if (prefix.empty() || std::isdigit(static_cast<unsigned char>(prefix[0]))) prefix = "piezo_" + prefix;
  }
  const std::string code = models::export_c99(*m, prefix);
  std::ofstream f(args.str("c-header"));
  if (!f) throw std::runtime_error(args.str("c-header") + ": cannot open for writing");
  f << code;
  if (!f) throw std::runtime_error(args.str("c-header") + ": write failed");
  std::cout << "wrote " << args.str("c-header") << " (prefix " << prefix << "_, kind " << m->kind() << ")\n";
  return 0;
}

const Register reg("export", "write a model as a dependency-free C99 header", run);

}  // namespace
}  // namespace piezo::cli
