// libFuzzer target for the file readers beyond the CAN codec, one binary, the reader chosen by
// PIEZO_FUZZ_READER: csv (io::read_csv), model (models::load_model), protocol (can::load_protocol_config),
// controller_log (io::import_controller_log, axis c, the MM3E's fine mode).
// Any input must give a result or the reader's one documented error type (io::DataError,
// models::ModelFileError, std::invalid_argument); anything else escaping, a sanitizer report, a huge
// allocation (-malloc_limit_mb) or a hang is a finding. The input is handed over as a file (memfd), as the
// readers take paths.
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <string>

#include "piezo_compensation/can/protocol.h"
#include "fuzz_input.h"
#include "piezo_compensation/io/controller_log.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model_file.h"

namespace {

enum class Reader { kCsv, kModel, kProtocol, kControllerLog };

Reader reader() {
  static const Reader r = [] {
    const char* v = std::getenv("PIEZO_FUZZ_READER");
    const std::string s = v ? v : "";
    if (s == "csv") return Reader::kCsv;
    if (s == "model") return Reader::kModel;
    if (s == "protocol") return Reader::kProtocol;
    if (s == "controller_log") return Reader::kControllerLog;
    std::fprintf(stderr, "fuzz_readers: set PIEZO_FUZZ_READER to csv, model, protocol or controller_log\n");
    std::abort();
  }();
  return r;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const Reader r = reader();
  const piezo::fuzz::InputFile input(data, size);
  if (!input.ok()) return 0;
  const std::string path = input.path();
  try {
    switch (r) {
      case Reader::kCsv: {
        const auto d = piezo::io::read_csv(path);
        (void)d.size();
        break;
      }
      case Reader::kModel: {
        const auto m = piezo::models::load_model(path);
        (void)m;
        break;
      }
      case Reader::kProtocol: {
        const auto c = piezo::can::load_protocol_config(path);
        piezo::can::validate(c);  // what it returns is valid
        break;
      }
      case Reader::kControllerLog: {
        piezo::io::ControllerLogOptions o;
        o.volts_per_step = 80.0 / 32768.0;
        o.nm_per_count = -20.0;
        piezo::io::ControllerLogReport report;
        const auto d = piezo::io::import_controller_log(path, o, &report);
        d.validate();  // what it returns is valid
        break;
      }
    }
  } catch (const std::exception& e) {
    const bool documented = ((r == Reader::kCsv || r == Reader::kControllerLog) &&
                             dynamic_cast<const piezo::io::DataError*>(&e)) ||
                            (r == Reader::kModel && dynamic_cast<const piezo::models::ModelFileError*>(&e)) ||
                            (r == Reader::kProtocol && dynamic_cast<const std::invalid_argument*>(&e));
    if (!documented) {
      std::fprintf(stderr, "fuzz_readers: undocumented exception: %s\n", e.what());
      std::abort();
    }
  }
  return 0;
}
