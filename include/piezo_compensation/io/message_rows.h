// A manipulator's recorded messages (per axis the voltage reports, encoder readings and simulated true positions,
// the aux signals, the protocol markers) made into the rows of a Dataset by the one rule: each axis' report,
// reading and truth paired by sequence number (io/sequence_pairer.h), fed in stamp order as the predictor would
// have heard them; one row per reading of the first axis whose sample every other axis has (a sample an axis
// lost is never filled from a neighbour, docs/data_formats.md). The bag reader (ros/data_file.h) and the
// predictor's warm-up on its in-memory snapshot (compensation/reload_warmup.h) both build their rows here.
#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include "piezo_compensation/io/dataset.h"

namespace piezo::io {

struct StampedValue {
  double stamp_s = 0.0;       // the header stamp (the sample clock)
  std::uint32_t sequence = 0;
  double value = 0.0;         // V for reports, nm for readings and truths, the signal's unit for aux
  bool valid = true;          // readings: false when the controller flagged it invalid
};

struct AxisMessages {
  std::vector<StampedValue> voltage, encoder, truth;
};

struct RecordedMessages {
  std::string source;         // names the data in errors (a file path)
  std::string ns;             // the manipulator namespace the topics are under, for errors ("" or e.g. "/mm1")
  AxisMessages axes[3];       // by index in kAxisNames; an axis with no message is not in the data set
  std::map<std::string, std::vector<StampedValue>> aux;          // by signal name
  std::vector<std::pair<double, std::pair<int, int>>> markers;   // stamp → (segment, phase code)
};

struct MessageRowOptions {
  std::vector<std::string>* gaps = nullptr;                 // one line per gap inside the data (BagOptions::gaps)
  std::vector<std::uint32_t>* row_sequences = nullptr;      // each row's sequence number
};

// The data set of `messages` (consumed: each stream is sorted by stamp, stably, and freed once paired).
// time_clock "ros"; source = messages.source. Throws DataError naming the source, the row and the column: an axis
// with readings but no reports (or the reverse), no reading, an axis none of whose samples pairs with the first
// axis', a reading flagged invalid at a row, a reading without a report before it, a missing truth, an aux signal
// or protocol marker starting after the first row.
Dataset dataset_from_messages(RecordedMessages&& messages, const MessageRowOptions& options = {});

}  // namespace piezo::io
