// The predictor's ~reload_model warm-up (docs/predictor.md, "Reload"): a new model streamed over the snapshot
// buffer's in-memory history, so it starts with the state of a model that had been running (low-pass and lag
// terms, creep) instead of at rest. The history is made into a data set by the one row rule of the bag reader
// (io/message_rows.h), so the warm-up pairs and aligns samples exactly as `piezo residual` did on the ~snapshot bag.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "piezo_compensation/compensation/snapshot_buffer.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"

namespace piezo::compensation {

// The snapshot as the data set its ~snapshot bag reads as (ros_io::read_bag): the same rows, columns and aux
// signals, on the ROS clock. row_sequences (optional): each row's sequence number. Throws io::DataError as the
// reader does (source "snapshot buffer").
io::Dataset snapshot_dataset(const Snapshot& s, std::vector<std::uint32_t>* row_sequences = nullptr);

// Streams `model` (free-run, from rest at the first row; models::stream_model) over the snapshot. Returns "" or why
// it could not (the caller then starts the model at rest). With `running` (the model running now) and an augmented
// `model` on the same base, the base's state and the offset are then taken from the running model
// (compensation/base_handover.h), its recorded predictions matched to the rows by sequence number (a sample another
// axis lost has no row); `handover` says what was done.
std::string warm_model(models::Model& model, const std::string& axis, const Snapshot& s,
                       const models::Model* running = nullptr, std::string* handover = nullptr);

}  // namespace piezo::compensation
