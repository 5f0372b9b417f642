// The model test matrix of issue 11: every kind on every simulated stage (three stages × PI-like/Preisach
// hysteresis × without/with creep, config/stages/*.yaml), fitted on the first 80 % and run free on the rest.
// The stage settings build the data only; the fits see the data set alone. Prints the matrix (docs/models.md).
// Set PIEZO_STAGE_MATRIX_FULL=1 for the MM3E stages' full 7.5 h (the default run uses 2 h to stay fast).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <map>
#include <set>

#include "piezo_compensation/analysis/model_selection.h"
#include "piezo_compensation/analysis/noise_floor.h"
#include "piezo_compensation/sim/stage.h"

using namespace piezo;

namespace {

const char* kStages[] = {"lowvolt", "stack150", "mm3e"};
const char* kPhysics[] = {"pi", "pi_creep", "preisach", "preisach_creep"};
const std::vector<std::string> kNeural = {"dense", "lstm", "kan"};

// The neural kinds train for a fixed number of optimiser steps (deterministic for the seed): their cells are
// reproducible and asserted like the others.
constexpr int kNeuralSteps = 800;

// Cells known to fail the 10 % criterion, with the measured figure and the reason (docs/models.md); every other
// cell must pass, and a listed cell that passes is reported. No kind's cell is listed: the neural kinds' default
// features are voltage history only (features::voltage_history_features) and dense/KAN start at the linear fit.
const std::map<std::string, std::string> kKnownFailing = {};

std::string matrix_header() {
  std::string md = "| stage | noise floor σ [nm] (MAE) | range [nm] |";
  std::vector<std::string> labels;
  for (const auto& c : analysis::default_candidates(kNeural)) labels.push_back(c.label);
  for (const auto& l : labels) md += " " + l + " |";
  md += " auto |\n|---|---|---|";
  for (std::size_t k = 0; k <= labels.size(); ++k) md += "---|";
  return md + "\n";
}

// One stage: every kind fitted on the first 80 %, scored free-run on the rest; returns the matrix row.
std::string stage_row(const std::string& name, bool full) {
  const std::string st = name.substr(0, name.find('_'));
  const auto stage = sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/" + name + ".yaml");
  const double duration_s = st == "mm3e" && !full ? 7200.0 : 0.0;
  const io::Dataset all = sim::simulate_stage(stage, 21, duration_s);
  const std::size_t cut = all.size() * 4 / 5;
  const io::Dataset train = all.slice(0, cut), val = all.slice(cut, all.size());
  analysis::SelectionRequest rq = analysis::selection_request(train, &val, all, cut, "c");
  rq.candidates = analysis::default_candidates(kNeural);
  for (auto& c : rq.candidates)
    if (std::count(kNeural.begin(), kNeural.end(), c.kind)) c.options = YAML::Load("{steps: " + std::to_string(kNeuralSteps) + ", patience: 0}");
  rq.seed = 3;
  analysis::Selection sel;
  try {
    sel = analysis::select_model(rq);
  } catch (const analysis::FitRejected& e) {
    ADD_FAILURE() << e.what();
    return "| " + name + " | **every kind refused** |\n";
  }
  const auto floor = analysis::estimate_noise_floor(val, "c");
  const double range = sel.scale.position_range_nm;
  char buf[160];
  std::snprintf(buf, sizeof buf, "| %s | %.3g (%.3g) | %.4g |", name.c_str(), floor.sigma_nm, floor.floor_mae_nm, range);
  std::string md = buf;
  const std::size_t n_default = analysis::default_candidates().size();
  double best_all = INFINITY, best_auto = INFINITY;
  std::set<std::string> failing;
  for (std::size_t k = 0; k < sel.table.size(); ++k) {
    const auto& r = sel.table[k];
    const bool scored = r.score.finite && r.score.free_run.valid();
    const double mae = scored ? r.score.free_run.mae_nm : INFINITY;
    const bool ok = r.refused.empty() && mae < 0.10 * range;
    const std::string cell = name + "/" + r.candidate.label;
    if (!ok) failing.insert(cell);
    if (scored)
      std::snprintf(buf, sizeof buf, " %.4g (%.2f %%)%s |", mae, 100.0 * mae / range,
                    r.refused.empty() ? (ok ? "" : " **>10 %**") : " **refused**");
    else
      std::snprintf(buf, sizeof buf, " **refused** |");
    md += buf;
    if (r.refused.empty()) {
      best_all = std::min(best_all, mae);
      if (k < n_default) best_auto = std::min(best_auto, mae);
    }
    if (!ok && !kKnownFailing.count(cell)) ADD_FAILURE() << cell << ": " << (r.refused.empty() ? "free-run MAE " + std::to_string(mae) + " nm ≥ 10 % of " + std::to_string(range) + " nm" : r.refused);
  }
  std::snprintf(buf, sizeof buf, " %.4g (%.2f %%) |\n", best_auto, 100.0 * best_auto / range);
  md += buf;
  std::printf("%s fit times [s]:", name.c_str());
  for (const auto& r : sel.table) std::printf(" %s %.1f,", r.candidate.label.c_str(), r.fit_s);
  std::printf(" of %zu + %zu samples\n", train.size(), val.size());
  // auto (linear on lasso features, pi, pi_creep_*) within 10 % of the best kind, neural ones included.
  const std::string cell = name + "/auto";
  if (!(best_auto <= 1.10 * best_all)) {
    failing.insert(cell);
    if (!kKnownFailing.count(cell)) ADD_FAILURE() << cell << ": auto " << best_auto << " nm, best kind " << best_all << " nm";
  }
  for (const auto& [known, why] : kKnownFailing)
    if (known.rfind(name + "/", 0) == 0 && !failing.count(known))
      std::printf("%s now passes (listed as failing: %s)\n", known.c_str(), why.c_str());
  return md;
}

std::vector<std::string> stage_names() {
  std::vector<std::string> out;
  for (const char* st : kStages)
    for (const char* ph : kPhysics) out.push_back(std::string(st) + "_" + ph);
  return out;
}

class StageMatrix : public testing::TestWithParam<std::string> {};

}  // namespace

// One test per stage (the stage families run as separate CTest tests in parallel, cmake/parts/stages.cmake);
// each prints its row of the matrix under the header.
TEST_P(StageMatrix, EveryKindHolds) {
  const bool full = std::getenv("PIEZO_STAGE_MATRIX_FULL") != nullptr;
  SCOPED_TRACE(GetParam());
  const std::string row = stage_row(GetParam(), full);
  std::printf("\nFree-run validation MAE [nm] (%% of the position range) per kind%s; neural kinds: %d optimiser steps, "
              "seed 3:\n\n%s%s\n", full ? "" : " (MM3E stages: 2 h)", kNeuralSteps, matrix_header().c_str(), row.c_str());
}

INSTANTIATE_TEST_SUITE_P(Stages, StageMatrix, testing::ValuesIn(stage_names()),
                         [](const testing::TestParamInfo<std::string>& i) { return i.param; });
