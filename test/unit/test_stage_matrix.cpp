// The model test matrix of issue 11: every kind on every simulated stage (three stages × PI-like/Preisach
// hysteresis × without/with creep, config/stages/*.yaml), fitted on the first 80 % and run free on the rest.
// The stage settings build the data only; the fits see the data set alone. Then every fitted kind runs on a
// separate recording of the stage (another seed, starting mid-motion, cold with the start estimate: issue 26
// item 4). Prints both matrices and the model choice (docs/models.md).
// Set PIEZO_STAGE_MATRIX_FULL=1 for the MM3E stages' full 7.5 h (the default run uses 2 h to stay fast).
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <map>
#include <set>

#include "piezo_compensation/analysis/model_selection.h"
#include "piezo_compensation/analysis/metrics.h"
#include "piezo_compensation/analysis/noise_floor.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/sim/stage.h"

using namespace piezo;

namespace {

const char* kStages[] = {"lowvolt", "stack150", "mm3e"};
const char* kPhysics[] = {"pi", "pi_creep", "preisach", "preisach_creep"};
const std::vector<std::string> kNeural = {"dense", "lstm", "kan"};

// The neural kinds train for a fixed number of optimiser steps (deterministic for the seed): their cells are
// reproducible and asserted like the others.
constexpr int kNeuralSteps = 800;

// Cells known to fail, with the measured figure and the reason (docs/models.md); every other cell must pass, and a
// listed cell that passes is reported. Names: "<stage>/<kind>" (continuation MAE ≥ 10 % of range), "<stage>/auto"
// (auto > 1.1× the best kind), "<stage>/<kind> separate" (separate recording > 1.5× the continuation),
// "<stage>/auto separate" (auto > 1.1× the best kind there).
// Separate-recording cells: the figure "separate nm, × the continuation nm" and the MAE from rest (no estimate).
std::string from_rest_too(const char* figure, const char* rest) {
  return std::string(figure) + "; from rest " + rest + " nm, also > 1.5×: the window leaves the state open and the "
         "scored part does not sweep it into agreement (the 50-µm stages' 13 s, creep; issue 26 item 1)";
}
std::string worse_than_rest(const char* figure, const char* rest) {
  return std::string(figure) + "; from rest " + rest + " nm passes: the chosen state or offset is "
         "wrong after the window (issue 26 item 1)";
}
const std::map<std::string, std::string> kKnownFailing = {
    {"lowvolt_pi/auto", "auto chose pi: 42.84 nm, best kind 38.27 nm; pi is within the paired-block noise of preisach on the 10-s tail and has fewer parameters"},
    {"lowvolt_pi/linear (lasso features) separate", from_rest_too("713.8, 3.744× 190.7", "8.265e+05")},
    {"lowvolt_pi/pi separate", from_rest_too("108.9, 2.543× 42.84", "373.1")},
    {"lowvolt_pi/preisach separate", from_rest_too("292.2, 7.636× 38.27", "211.1")},
    {"lowvolt_pi/kan separate", from_rest_too("130.4, 1.533× 85.04", "558.6")},
    {"lowvolt_pi/lstm separate", worse_than_rest("4273, 2.127× 2009", "2918")},
    {"lowvolt_pi/auto separate", "auto chose pi: 108.9 nm on the separate recording, best kind 50.39 nm; auto chooses on the training recording (its cold fold starts from rest, without the estimate)"},
    {"lowvolt_pi_creep/linear (lasso features) separate", from_rest_too("823.8, 3.001× 274.5", "2.03e+04")},
    {"lowvolt_pi_creep/pi separate", from_rest_too("437.6, 2.688× 162.8", "1285")},
    {"lowvolt_pi_creep/pi_creep_fractional separate", from_rest_too("640.9, 5.885× 108.9", "495.2")},
    {"lowvolt_pi_creep/pi_creep_log separate", from_rest_too("943.2, 6.11× 154.4", "496")},
    {"lowvolt_pi_creep/pi_creep_lti separate", from_rest_too("684.4, 3.309× 206.8", "358.4")},
    {"lowvolt_pi_creep/pi_creep_prony separate", from_rest_too("668.2, 3.708× 180.2", "351.5")},
    {"lowvolt_pi_creep/preisach separate", from_rest_too("565.8, 3.418× 165.5", "1386")},
    {"lowvolt_pi_creep/kan separate", from_rest_too("576.1, 8.99× 64.08", "1392")},
    {"lowvolt_pi_creep/dense separate", from_rest_too("702.8, 2.959× 237.5", "1438")},
    {"lowvolt_pi_creep/lstm separate", from_rest_too("5390, 2.568× 2099", "3200")},
    {"lowvolt_pi_creep/auto separate", "auto chose kan: 576.1 nm on the separate recording, best kind 94.98 nm; auto chooses on the training recording (its cold fold starts from rest, without the estimate)"},
    {"lowvolt_preisach/linear (lasso features) separate", from_rest_too("2155, 2.953× 729.9", "1.919e+04")},
    {"lowvolt_preisach/pi_creep_log separate", from_rest_too("1328, 1.562× 850.4", "3125")},
    {"lowvolt_preisach/pi_creep_lti separate", from_rest_too("1201, 1.552× 773.8", "3154")},
    {"lowvolt_preisach/kan separate", from_rest_too("632.4, 1.812× 348.9", "2642")},
    {"lowvolt_preisach/lstm separate", from_rest_too("5607, 3.433× 1633", "3454")},
    {"lowvolt_preisach_creep/linear (lasso features) separate", from_rest_too("2111, 2.265× 931.7", "1.939e+04")},
    {"lowvolt_preisach_creep/pi_creep_log separate", from_rest_too("1307, 1.526× 856.2", "3369")},
    {"lowvolt_preisach_creep/preisach separate", from_rest_too("686.7, 1.597× 429.9", "1634")},
    {"lowvolt_preisach_creep/preisach_creep_prony separate", worse_than_rest("738.9, 2.19× 337.4", "361")},
    {"lowvolt_preisach_creep/lstm separate", from_rest_too("4671, 2.656× 1758", "3842")},
    {"lowvolt_preisach_creep/auto separate", "auto chose preisach_creep_prony: 738.9 nm on the separate recording, best kind 323 nm; auto chooses on the training recording (its cold fold starts from rest, without the estimate)"},
    {"stack150_pi/linear (lasso features) separate", from_rest_too("1.072e+08, 7.922e+05× 135.4", "1.585e+10")},
    {"stack150_pi/dense separate", from_rest_too("61.62, 2.331× 26.43", "77.72")},
    {"stack150_pi/lstm separate", from_rest_too("1300, 2.013× 646", "1303")},
    {"stack150_pi_creep/linear (lasso features) separate", from_rest_too("1.18e+08, 7.623e+05× 154.8", "1.75e+10")},
    {"stack150_pi_creep/pi_creep_fractional separate", from_rest_too("41.59, 1.915× 21.71", "289.4")},
    {"stack150_pi_creep/pi_creep_lti separate", from_rest_too("34.23, 1.992× 17.18", "78.48")},
    {"stack150_pi_creep/pi_creep_prony separate", from_rest_too("37.42, 1.701× 22", "130.5")},
    {"stack150_pi_creep/preisach separate", worse_than_rest("139.1, 1.518× 91.66", "79.19")},
    {"stack150_pi_creep/preisach_creep_prony separate", from_rest_too("77.67, 4.791× 16.21", "575.5")},
    {"stack150_pi_creep/dense separate", from_rest_too("78.4, 2.959× 26.5", "81.52")},
    {"stack150_pi_creep/lstm separate", from_rest_too("1330, 1.955× 680.1", "1321")},
    {"stack150_pi_creep/auto separate", "auto chose pi_creep_lti: 34.23 nm on the separate recording, best kind 24.23 nm; auto chooses on the training recording (its cold fold starts from rest, without the estimate)"},
    {"stack150_preisach/linear (lasso features) separate", from_rest_too("483.8, 2.484× 194.8", "3254")},
    {"stack150_preisach/preisach_creep_prony separate", worse_than_rest("31.26, 1.522× 20.54", "30.06")},
    {"stack150_preisach/dense separate", from_rest_too("274.1, 2.319× 118.2", "371.8")},
    {"stack150_preisach/lstm separate", from_rest_too("3211, 4.558× 704.6", "1460")},
    {"stack150_preisach_creep/linear (lasso features) separate", from_rest_too("685.9, 3.419× 200.6", "3217")},
    {"stack150_preisach_creep/preisach_creep_prony separate", from_rest_too("84.93, 2.749× 30.89", "120.7")},
    {"stack150_preisach_creep/dense separate", from_rest_too("278.2, 2.28× 122", "529.8")},
    {"stack150_preisach_creep/lstm separate", from_rest_too("1443, 1.93× 748", "1475")},
    {"mm3e_pi/lstm separate", from_rest_too("113.9, 5.6× 20.34", "73.28")},
    {"mm3e_pi_creep/linear (lasso features) separate", from_rest_too("33.79, 1.905× 17.74", "35.02")},
    {"mm3e_pi_creep/pi separate", from_rest_too("49.84, 1.77× 28.16", "48.67")},
    {"mm3e_pi_creep/pi_creep_fractional separate", from_rest_too("32.51, 1.911× 17.02", "70.66")},
    {"mm3e_pi_creep/pi_creep_lti separate", from_rest_too("25.84, 1.519× 17.01", "35.08")},
    {"mm3e_pi_creep/pi_creep_prony separate", from_rest_too("60.75, 3.577× 16.98", "61.6")},
    {"mm3e_pi_creep/preisach separate", from_rest_too("44.6, 1.623× 27.48", "46.99")},
    {"mm3e_pi_creep/preisach_creep_prony separate", from_rest_too("106.3, 6.313× 16.83", "86.75")},
    {"mm3e_pi_creep/kan separate", from_rest_too("27.57, 1.568× 17.58", "27.82")},
    {"mm3e_pi_creep/dense separate", from_rest_too("36.16, 2.103× 17.19", "48")},
    {"mm3e_pi_creep/lstm separate", from_rest_too("139.3, 6.229× 22.36", "113.5")},
    {"mm3e_pi_creep/auto separate", "auto chose preisach_creep_prony: 106.3 nm on the separate recording, best kind 24.47 nm; auto chooses on the training recording (its cold fold starts from rest, without the estimate)"},
    {"mm3e_preisach/kan separate", from_rest_too("43.18, 2.396× 18.02", "41.01")},
    {"mm3e_preisach/dense separate", from_rest_too("69.24, 3.639× 19.03", "59.52")},
    {"mm3e_preisach/lstm separate", from_rest_too("113.2, 5.598× 20.21", "71.84")},
    {"mm3e_preisach/auto separate", "auto chose kan: 43.18 nm on the separate recording, best kind 17.52 nm; auto chooses on the training recording (its cold fold starts from rest, without the estimate)"},
    {"mm3e_preisach_creep/pi separate", from_rest_too("68.99, 2.494× 27.67", "59.55")},
    {"mm3e_preisach_creep/pi_creep_fractional separate", from_rest_too("91.68, 2.38× 38.52", "66.9")},
    {"mm3e_preisach_creep/pi_creep_log separate", worse_than_rest("88.48, 2.057× 43.01", "61.72")},
    {"mm3e_preisach_creep/pi_creep_lti separate", worse_than_rest("97.6, 2.214× 44.07", "59.92")},
    {"mm3e_preisach_creep/pi_creep_prony separate", worse_than_rest("97.52, 2.15× 45.37", "60.26")},
    {"mm3e_preisach_creep/preisach_creep_prony separate", from_rest_too("120.3, 6.846× 17.58", "115.3")},
    {"mm3e_preisach_creep/kan separate", from_rest_too("67.45, 3.632× 18.57", "57.22")},
    {"mm3e_preisach_creep/dense separate", from_rest_too("75.92, 3.569× 21.27", "93.82")},
    {"mm3e_preisach_creep/lstm separate", from_rest_too("150.9, 5.626× 26.83", "117.5")},
    {"mm3e_preisach_creep/auto separate", "auto chose preisach_creep_prony: 120.3 nm on the separate recording, best kind 25.66 nm; auto chooses on the training recording (its cold fold starts from rest, without the estimate)"},
};

std::string matrix_header() {
  std::string md = "| stage | noise floor σ [nm] (MAE) | range [nm] |";
  std::vector<std::string> labels;
  for (const auto& c : analysis::default_candidates(kNeural)) labels.push_back(c.label);
  for (const auto& l : labels) md += " " + l + " |";
  md += " auto |\n|---|---|---|";
  for (std::size_t k = 0; k <= labels.size(); ++k) md += "---|";
  return md + "\n";
}

// The separate recording of a stage family: length simulated, first part dropped (the history then starts
// mid-motion, at a state the model cannot know), and the start-estimate window; sized to the stage's rate and
// its walk's correlation time (lowvolt 0.6 s, stack150 0.3 s, MM3E minutes) while keeping the test fast.
struct SeparateSpec {
  double duration_s, cut_s, anchor_s;
};
SeparateSpec separate_spec(const std::string& family) {
  if (family == "lowvolt") return {20.0, 5.0, 2.0};
  if (family == "stack150") return {8.0, 2.0, 1.0};
  return {3600.0, 900.0, 30.0};
}
constexpr std::uint64_t kSeparateSeed = 22;
constexpr double kSeparateRatio = 1.5;  // separate-recording error / continuation error, per kind
constexpr double kAutoMargin = 1.10;    // auto's error / the best kind's, on either recording

// Another recording of the stage (another seed), cut at the first sample at or after cut_s where the voltage
// moves (not at rest, where any start state would look right for a while).
io::Dataset separate_recording(const sim::StageConfig& stage, const SeparateSpec& s, double* cut_at_s) {
  const io::Dataset rec = sim::simulate_stage(stage, kSeparateSeed, s.duration_s);
  const auto& v = rec.axis("c").voltage_v;
  std::size_t cut = static_cast<std::size_t>(std::lround(s.cut_s * rec.sample_rate_hz()));
  while (cut + 1 < v.size() && (v[cut] == v[cut - 1] || v[cut + 1] == v[cut])) ++cut;
  *cut_at_s = rec.time_s[cut] - rec.time_s[0];
  return rec.slice(cut, rec.size());
}

// Free-run MAE vs the measurement on the separate recording from a cold state, scored after its first anchor_s:
// with the start estimate over that window (the criterion), and from rest alone (for comparison).
struct SeparateMae {
  double estimate = INFINITY, rest = INFINITY;
};
SeparateMae separate_mae(const models::Model& model, const io::Dataset& d, double anchor_s) {
  models::StreamOptions o;
  o.anchor_s = anchor_s;
  o.keep_diverging = true;
  const auto& y = d.axis("c").position_nm;
  SeparateMae out;
  auto m = model.clone();
  const models::StreamResult r = models::stream_model(*m, d, "c", o);
  const std::vector<char> mask = models::scored_mask(r, d.size());
  out.estimate = analysis::error_stats(r.prediction, y, mask).mae_nm;
  o.anchor_s = 0.0;
  m = model.clone();
  out.rest = analysis::error_stats(models::stream_model(*m, d, "c", o).prediction, y, mask).mae_nm;
  return out;
}

// Records a failing cell (asserted unless listed as known) and reports a listed cell that passes.
struct CellCheck {
  const std::map<std::string, std::string>& known;
  std::set<std::string> failing;
  void fail(const std::string& cell, const std::string& why) {
    failing.insert(cell);
    if (!known.count(cell)) ADD_FAILURE() << cell << ": " << why;
  }
  void report_passing(const std::string& stage) const {
    for (const auto& [cell, why] : known)
      if (cell.rfind(stage + "/", 0) == 0 && !failing.count(cell))
        std::printf("%s now passes (listed as failing: %s)\n", cell.c_str(), why.c_str());
  }
};

std::string figure(double x) {
  char b[32];
  std::snprintf(b, sizeof b, "%.4g", x);
  return b;
}

struct StageFit {
  analysis::Selection sel;
  io::Dataset val;
  std::size_t train_size = 0;
  bool ok = false;
};

// Every kind fitted on the first 80 % of seed 21's recording; scored free-run on the rest by select_model.
StageFit fit_stage(const std::string& name, const sim::StageConfig& stage, bool full) {
  const std::string st = name.substr(0, name.find('_'));
  const double duration_s = st == "mm3e" && !full ? 7200.0 : 0.0;
  const io::Dataset all = sim::simulate_stage(stage, 21, duration_s);
  const std::size_t cut = all.size() * 4 / 5;
  const io::Dataset train = all.slice(0, cut);
  StageFit f;
  f.val = all.slice(cut, all.size());
  f.train_size = train.size();
  analysis::SelectionRequest rq = analysis::selection_request(train, &f.val, all, cut, "c");
  rq.candidates = analysis::default_candidates(kNeural);
  for (auto& c : rq.candidates)
    if (std::count(kNeural.begin(), kNeural.end(), c.kind)) c.options = YAML::Load("{steps: " + std::to_string(kNeuralSteps) + ", patience: 0}");
  rq.seed = 3;
  try {
    f.sel = analysis::select_model(rq);
    f.ok = true;
  } catch (const analysis::FitRejected& e) {
    ADD_FAILURE() << e.what();
  }
  return f;
}

// What `piezo fit --model auto` chooses: choose_candidate (the call select_model makes) over auto's own
// candidates, the first default_candidates() of the table; dense and lstm are scored beside them, not offered.
std::size_t auto_choice(const analysis::Selection& sel) {
  const std::size_t n = std::min(analysis::default_candidates().size(), sel.table.size());
  std::vector<analysis::ChoiceEntry> entries;
  for (std::size_t k = 0; k < n; ++k) {
    const auto& r = sel.table[k];
    entries.push_back({r.candidate.label, r.parameters, r.refused.empty() && r.slow.valid() ? &r.slow : nullptr});
  }
  const std::size_t chosen = analysis::choose_candidate(entries).chosen;
  return chosen == SIZE_MAX ? sel.best : chosen;
}

double continuation_mae(const analysis::CandidateResult& r) {
  return r.score.finite && r.score.free_run.valid() ? r.score.free_run.mae_nm : INFINITY;
}

// The continuation row: every kind's free-run validation MAE; auto = the kind `--model auto` chooses.
std::string continuation_row(const std::string& name, const StageFit& f, CellCheck& check) {
  const auto& sel = f.sel;
  const auto floor = analysis::estimate_noise_floor(f.val, "c");
  const double range = sel.scale.position_range_nm;
  char buf[200];
  std::snprintf(buf, sizeof buf, "| %s | %.3g (%.3g) | %.4g |", name.c_str(), floor.sigma_nm, floor.floor_mae_nm, range);
  std::string md = buf;
  double best = INFINITY;
  for (const auto& r : sel.table) {
    const double mae = continuation_mae(r);
    const bool ok = r.refused.empty() && mae < 0.10 * range;
    if (std::isfinite(mae))
      std::snprintf(buf, sizeof buf, " %.4g (%.2f %%)%s |", mae, 100.0 * mae / range,
                    r.refused.empty() ? (ok ? "" : " **>10 %**") : " **refused**");
    else
      std::snprintf(buf, sizeof buf, " **refused** |");
    md += buf;
    if (r.refused.empty()) best = std::min(best, mae);
    if (!ok)
      check.fail(name + "/" + r.candidate.label,
                 r.refused.empty() ? "free-run MAE " + figure(mae) + " nm ≥ 10 % of " + figure(range) + " nm" : r.refused);
  }
  const auto& chosen = sel.table[auto_choice(sel)];
  const double auto_mae = continuation_mae(chosen);
  std::snprintf(buf, sizeof buf, " %s %.4g (%.2f %%) |\n", chosen.candidate.label.c_str(), auto_mae, 100.0 * auto_mae / range);
  md += buf;
  if (!(auto_mae <= kAutoMargin * best))
    check.fail(name + "/auto", "auto chose " + chosen.candidate.label + ": " + figure(auto_mae) + " nm, best kind " + figure(best) + " nm");
  return md;
}

// The separate-recording row: every kind's MAE there and its ratio to the continuation; auto = its choice.
std::string separate_row(const std::string& name, const StageFit& f, const io::Dataset& rec, double anchor_s,
                         CellCheck& check) {
  const auto& sel = f.sel;
  std::string md = "| " + name + " |";
  std::vector<double> sep(sel.table.size(), INFINITY);
  double best = INFINITY;
  for (std::size_t k = 0; k < sel.table.size(); ++k) {
    const auto& r = sel.table[k];
    if (!r.model) {
      md += " refused |";
      continue;
    }
    const SeparateMae e = separate_mae(*r.model, rec, anchor_s);
    sep[k] = e.estimate;
    best = std::min(best, sep[k]);
    const double ratio = sep[k] / continuation_mae(r);
    const bool ok = ratio <= kSeparateRatio;
    char buf[120];
    std::snprintf(buf, sizeof buf, " %.4g (%.2f×)%s; rest %.4g |", sep[k], ratio, ok ? "" : " **>1.5×**", e.rest);
    md += buf;
    if (!ok)
      check.fail(name + "/" + r.candidate.label + " separate",
                 figure(sep[k]) + " nm on the separate recording, " + figure(ratio) + "× the continuation's " +
                     figure(continuation_mae(r)) + " nm");
  }
  const std::size_t chosen = auto_choice(sel);
  const double a = sep[chosen];
  char buf[120];
  std::snprintf(buf, sizeof buf, " %s %.4g (%.2f× the best) |\n", sel.table[chosen].candidate.label.c_str(), a, a / best);
  md += buf;
  if (!(a <= kAutoMargin * best))
    check.fail(name + "/auto separate", "auto chose " + sel.table[chosen].candidate.label + ": " + figure(a) +
                                            " nm on the separate recording, best kind " + figure(best) + " nm");
  return md;
}

std::string separate_header() {
  std::string md = "| stage |";
  std::size_t n = 0;
  for (const auto& c : analysis::default_candidates(kNeural)) md += " " + c.label + " |", ++n;
  md += " auto (its choice) |\n|---|";
  for (std::size_t k = 0; k <= n; ++k) md += "---|";
  return md + "\n";
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
// each prints its rows of the two matrices under their headers.
TEST_P(StageMatrix, EveryKindHolds) {
  const bool full = std::getenv("PIEZO_STAGE_MATRIX_FULL") != nullptr;
  const std::string name = GetParam();
  SCOPED_TRACE(name);
  const auto stage = sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/" + name + ".yaml");
  const StageFit f = fit_stage(name, stage, full);
  if (!f.ok) return;
  CellCheck check{kKnownFailing, {}};
  const std::string row = continuation_row(name, f, check);
  std::printf("%s fit times [s]:", name.c_str());
  for (const auto& r : f.sel.table) std::printf(" %s %.1f,", r.candidate.label.c_str(), r.fit_s);
  std::printf(" of %zu + %zu samples\n\n%s\n", f.train_size, f.val.size(), analysis::selection_table(f.sel).c_str());
  std::printf("\nFree-run validation MAE [nm] (%% of the position range) per kind%s; neural kinds: %d optimiser steps, "
              "seed 3:\n\n%s%s\n", full ? "" : " (MM3E stages: 2 h)", kNeuralSteps, matrix_header().c_str(), row.c_str());
  const SeparateSpec spec = separate_spec(name.substr(0, name.find('_')));
  double cut_at_s = 0.0;
  const io::Dataset rec = separate_recording(stage, spec, &cut_at_s);
  const auto t0 = std::chrono::steady_clock::now();
  const std::string sep = separate_row(name, f, rec, spec.anchor_s, check);
  const double run_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::printf("Separate recording (seed %llu, %.0f s simulated, from %.2f s on, start estimate over %.3g s, scored "
              "after it; %.1f s to run every kind): free-run MAE [nm] (× the continuation's):\n\n%s%s\n",
              static_cast<unsigned long long>(kSeparateSeed), spec.duration_s, cut_at_s, spec.anchor_s, run_s,
              separate_header().c_str(), sep.c_str());
  check.report_passing(name);
}

INSTANTIATE_TEST_SUITE_P(Stages, StageMatrix, testing::ValuesIn(stage_names()),
                         [](const testing::TestParamInfo<std::string>& i) { return i.param; });
