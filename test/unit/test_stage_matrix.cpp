// The model test matrix: every kind on every simulated stage (three stages × PI-like/Preisach
// hysteresis × without/with creep, config/stages/*.yaml), fitted on the first 80 % and run free on the rest.
// The stage settings build the data only; the fits see the data set alone. Then every fitted kind runs on a
// separate recording of the stage (another seed, starting mid-motion, cold with the start estimate). Prints both
// matrices and the model choice (docs/validation/models.md, "The stage matrix").
// Set PIEZO_STAGE_MATRIX_FULL=1 for the MM3E stages' full 7.5 h (the default run uses 2 h to stay fast).
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <map>
#include <set>

#include "piezo_compensation/analysis/selection/model_selection.h"
#include "piezo_compensation/analysis/evaluation/metrics.h"
#include "piezo_compensation/analysis/evaluation/noise_floor.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/start_state.h"
#include "piezo_compensation/sim/stage.h"

using namespace piezo;

namespace {

const char* kStages[] = {"lowvolt", "stack150", "mm3e"};
const char* kPhysics[] = {"pi", "pi_creep", "preisach", "preisach_creep"};
const std::vector<std::string> kNeural = {"dense", "lstm", "kan"};

// The neural kinds train for a fixed number of optimiser steps (deterministic for the seed): their cells are
// reproducible and asserted like the others.
constexpr int kNeuralSteps = 800;

// Cells known to fail, with the figure they fail by and the reason (docs/validation/models.md); every other cell must pass, and a
// listed cell that passes is reported. Names: "<stage>/<kind>" (continuation MAE ≥ 10 % of range), "<stage>/auto"
// (auto > 1.1× the best kind), "<stage>/<kind> separate" (separate recording > 1.5× the continuation),
// "<stage>/auto separate" (auto > 1.1× the best kind there).
// Separate-recording cells: "separate nm, × the continuation nm" and the same model run over the whole recording
// (its history known, offset fixed on the same window): whole > 1.5× too means the model does not carry over to
// the other recording, whatever its start; whole ≤ 1.5× means the start estimate leaves the gap.
std::string not_carried_over(const char* figure, const char* whole) {
  return std::string(figure) + "; whole history " + whole + "× too: the model does not carry over to another "
         "recording";
}
std::string start_gap(const char* figure, const char* whole) {
  return std::string(figure) + "; whole history " + whole + "×: the start estimate leaves the gap";
}
const std::map<std::string, std::string> kKnownFailing = {
    {"lowvolt_pi/auto", "auto chose pi, 42.84 nm against the best kind's 38.27: auto chooses on the moves and the "
                        "hold creep, where pi is within the noise of the lowest overall (preisach_creep_prony)"},
    {"lowvolt_pi/auto separate", "auto chose pi, 142.3 nm against the best kind's 49.47 on the separate recording: "
                                 "pi does not carry over to it (lowvolt_pi/pi separate)"},
    {"lowvolt_pi/pi separate", not_carried_over("142.3, 3.32× 42.84", "2.794")},
    {"lowvolt_pi/pi_creep_fractional separate", start_gap("160.7, 1.59× 101", "1.191")},
    {"lowvolt_pi/pi_creep_log separate", start_gap("166.2, 1.56× 106.4", "1.214")},
    {"lowvolt_pi/pi_creep_lti separate", start_gap("160.5, 1.62× 99.25", "1.182")},
    {"lowvolt_pi/pi_creep_prony separate", start_gap("160.5, 1.62× 99.25", "1.182")},
    {"lowvolt_pi/dense separate", not_carried_over("211.1, 2.73× 77.31", "3.01")},
    {"lowvolt_pi_creep/pi separate", not_carried_over("548.1, 3.37× 162.8", "4.13")},
    {"lowvolt_pi_creep/pi_creep_fractional separate", start_gap("174.5, 1.60× 108.9", "1.054")},
    {"lowvolt_pi_creep/pi_creep_lti separate", start_gap("332.9, 1.61× 206.8", "0.8443")},
    {"lowvolt_pi_creep/pi_creep_prony separate", start_gap("317.8, 1.76× 180.2", "0.8749")},
    {"lowvolt_pi_creep/preisach separate", not_carried_over("506.5, 3.06× 165.5", "5.094")},
    {"lowvolt_pi_creep/preisach_creep_prony separate", start_gap("331.8, 3.74× 88.6", "1.487")},
    {"lowvolt_pi_creep/auto separate", "auto chose preisach_creep_prony: 331.8 nm on the separate recording, 1.90× the best kind (pi_creep_fractional 174.5 nm); best on the carry-over fold (423 nm against 698)"},
    {"lowvolt_preisach/pi_creep_log separate", not_carried_over("1276, 1.50× 850.4", "2.13")},
    {"lowvolt_preisach/pi_creep_lti separate", not_carried_over("1225, 1.58× 773.8", "2.044")},
    {"lowvolt_preisach_creep/lstm separate", not_carried_over("2122, 2.03× 1044", "2.63")},
    {"lowvolt_preisach_creep/kan separate", not_carried_over("418.5, 1.87× 223.5", "1.664")},
    {"lowvolt_preisach_creep/dense separate", not_carried_over("351.2, 1.92× 182.9", "1.56")},
    {"lowvolt_preisach_creep/auto", "auto chose preisach_creep_prony: 337.4 nm on the 10-s tail, best kind dense 182.9 nm (not an auto candidate), among auto's candidates linear (lasso features) 212.9 nm; the carry-over and cold folds reject the linear fit (1040 and 4590 nm against 527 and 1490), which with its history known does worse than preisach_creep_prony on the separate recording (356.8 nm against 340.5): the choice is for the next recording"},
    {"lowvolt_preisach_creep/auto separate", "auto chose preisach_creep_prony: 324.4 nm on the separate recording, 1.33× the best kind (linear (lasso features) 243.7 nm); with the history known preisach_creep_prony is the better (340.5 nm against 356.8): the start estimate decides this cell"},
    {"stack150_pi_creep/linear (lasso features) separate", start_gap("47.8, 1.76× 27.13", "0.8597")},
    {"stack150_pi_creep/preisach separate", start_gap("139.1, 1.52× 91.66", "1.157")},
    {"stack150_pi_creep/preisach_creep_prony separate", not_carried_over("27.58, 1.70× 16.21", "1.733")},
    {"stack150_pi_creep/auto separate", "auto chose pi_creep_lti: 18.66 nm on the separate recording, 1.26× the best kind (pi_creep_prony 14.77 nm), the lowest overall on the training recording (20.4 nm against 22.5: moves 16.6 against 21.2)"},
    {"stack150_preisach/preisach_creep_prony separate", not_carried_over("56.26, 2.74× 20.54", "1.913")},
    {"stack150_preisach/auto", "auto chose preisach: 23.07 nm on the 5-s tail, best kind preisach_creep_prony 20.54 nm; the carry-over fold prefers preisach (28.1 against 36.2 nm), the best kind on the separate recording (31.29 nm against 56.38): the choice is for the next recording"},
    {"mm3e_pi_creep/kan separate", start_gap("32.05, 1.88× 17.01", "1.003")},
    {"mm3e_preisach_creep/auto separate", "auto chose preisach_creep_prony: 23.09 nm on the separate recording, 1.12× the best kind (linear (lasso features) 20.6 nm); with the history known preisach_creep_prony is the better (17.16 nm against 17.68): its start gap (1.31× against 0.98× with the history known) decides this cell"},
    {"mm3e_preisach_creep/pi separate", not_carried_over("58.97, 2.13× 27.67", "2.19")},
    {"mm3e_preisach_creep/pi_creep_fractional separate", not_carried_over("58.68, 1.52× 38.52", "1.53")},
};

bool output_map_label(const std::string& l) {
  const std::string tail = " + output map";
  return l.size() > tail.size() && l.compare(l.size() - tail.size(), tail.size(), tail) == 0;
}

std::string matrix_header() {
  std::string md = "| stage | noise floor σ [nm] (MAE) | range [nm] |";
  std::vector<std::string> labels;
  for (const auto& c : analysis::default_candidates(kNeural))
    if (!output_map_label(c.label)) labels.push_back(c.label);
  for (const auto& l : labels) md += " " + l + " |";
  md += " auto |\n|---|---|---|";
  for (std::size_t k = 0; k <= labels.size(); ++k) md += "---|";
  return md + "\n";
}

// The separate recording of a stage family: length simulated, first part dropped (the history then starts
// mid-motion, at a state the model cannot know), and the start-estimate window; sized to the stage's rate and
// its walk's trend correlation time (lowvolt 0.6 s, stack150 0.3 s, MM3E 120 s: the window is 2.5–3.3 of them, so
// the voltage sweeps most of its range in it) while keeping the test fast (docs/models.md: the error by window).
struct SeparateSpec {
  double duration_s, cut_s, anchor_s;
};
SeparateSpec separate_spec(const std::string& family) {
  if (family == "lowvolt") return {20.0, 5.0, 2.0};
  if (family == "stack150") return {8.0, 2.0, 1.0};
  return {3600.0, 900.0, 300.0};
}
// The separate recording's seed: 22. PIEZO_STAGE_MATRIX_SEPARATE_SEED=N measures another seed's recordings (the
// known-failing list is seed 22's, so cells then fail or are reported as passing; docs/models.md's seeds 23, 24).
std::uint64_t separate_seed() {
  const char* s = std::getenv("PIEZO_STAGE_MATRIX_SEPARATE_SEED");
  return s && *s ? std::stoull(s) : 22;
}
constexpr double kSeparateRatio = 1.5;  // separate-recording error / continuation error, per kind
constexpr double kAutoMargin = 1.10;    // auto's error / the best kind's, on either recording

// Another recording of the stage (another seed), cut at the first sample at or after cut_s where the voltage
// moves (not at rest, where any start state would look right for a while): `part` is the recording from the cut,
// `whole` all of it (for the bound).
struct SeparateRecording {
  io::Dataset whole, part;
  std::size_t cut = 0;
  double cut_at_s = 0;
};
SeparateRecording separate_recording(const sim::StageConfig& stage, const SeparateSpec& s) {
  SeparateRecording r;
  r.whole = sim::simulate_stage(stage, separate_seed(), s.duration_s);
  const auto& v = r.whole.axis("c").voltage_v;
  std::size_t cut = static_cast<std::size_t>(std::lround(s.cut_s * r.whole.sample_rate_hz()));
  while (cut + 1 < v.size() && (v[cut] == v[cut - 1] || v[cut + 1] == v[cut])) ++cut;
  r.cut = cut;
  r.cut_at_s = r.whole.time_s[cut] - r.whole.time_s[0];
  r.part = r.whole.slice(cut, r.whole.size());
  return r;
}

// Free-run MAE vs the measurement on the separate recording from a cold state, scored after its first anchor_s:
// with the start estimate over that window (the criterion); from rest alone; and the bound: the model run over
// the whole recording from the simulator's own start (its history known), its offset fixed on the same window.
struct SeparateMae {
  double estimate = INFINITY, rest = INFINITY, whole = INFINITY;
  double swept = 0;  // the fraction of the model's training voltage range the start window swept
};
// `bounds` false: the criterion alone (rest and whole stay infinite), for rows that print only it.
SeparateMae separate_mae(const models::Model& model, const SeparateRecording& rec, double anchor_s,
                         bool bounds = true) {
  const io::Dataset& d = rec.part;
  models::StreamOptions o;
  o.anchor_s = anchor_s;
  o.keep_diverging = true;
  const auto& y = d.axis("c").position_nm;
  SeparateMae out;
  auto m = model.clone();
  const models::StreamResult r = models::stream_model(*m, d, "c", o);
  const std::vector<char> mask = models::scored_mask(r, d.size());
  out.estimate = analysis::error_stats(r.prediction, y, mask).mae_nm;
  out.swept = r.start.swept_fraction();
  if (!bounds) return out;
  o.anchor_s = 0.0;
  m = model.clone();
  out.rest = analysis::error_stats(models::stream_model(*m, d, "c", o).prediction, y, mask).mae_nm;
  m = model.clone();
  const std::vector<double> full = models::stream_model(*m, rec.whole, "c", o).prediction;
  std::vector<double> p(full.begin() + static_cast<long>(rec.cut), full.end());
  const models::WindowFit f = models::window_offset(y.data(), p.data(), r.first_scored);
  for (double& x : p) x += f.offset_nm;
  out.whole = analysis::error_stats(p, y, mask).mae_nm;
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

// A kind's output-map variant among auto's candidates (analysis::default_candidates): a variant, not a kind.
bool output_map_row(const analysis::CandidateResult& r) { return output_map_label(r.candidate.label); }

// What `piezo fit --model auto` chooses: choose_candidate (the call select_model makes) over auto's own
// candidates, the first default_candidates() of the table; the neural kinds are scored beside them, not offered.
std::size_t auto_choice(const analysis::Selection& sel) {
  const std::size_t n = std::min(analysis::default_candidates().size(), sel.table.size());
  std::vector<analysis::ChoiceEntry> entries;
  std::vector<std::size_t> rows;  // the table row of each entry
  for (std::size_t k = 0; k < n; ++k) {
    const auto& r = sel.table[k];
    entries.push_back({r.candidate.label, r.parameters, r.refused.empty() && r.slow.valid() ? &r.slow : nullptr});
    rows.push_back(k);
  }
  const std::size_t chosen = analysis::choose_candidate(entries).chosen;
  return chosen == SIZE_MAX ? sel.best : rows[chosen];
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
    if (output_map_row(r)) continue;  // auto's variant of its first choice: scored in the auto cell only
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
// `notes`: the start window's sweep and which of auto's candidates are within kAutoMargin of the best kind on both
// recordings (none: no choice can pass both auto cells with these fits).
std::string separate_row(const std::string& name, const StageFit& f, const SeparateRecording& rec, double anchor_s,
                         CellCheck& check, std::string& notes) {
  const auto& sel = f.sel;
  std::string md = "| " + name + " |";
  std::vector<double> sep(sel.table.size(), INFINITY);
  double best = INFINITY, swept = 0;
  for (std::size_t k = 0; k < sel.table.size(); ++k) {
    const auto& r = sel.table[k];
    if (output_map_row(r)) {  // auto's variant of its first choice: scored in the auto cell only
      if (r.model) sep[k] = separate_mae(*r.model, rec, anchor_s, false).estimate;
      continue;
    }
    if (!r.model) {
      md += " refused |";
      continue;
    }
    const SeparateMae e = separate_mae(*r.model, rec, anchor_s);
    sep[k] = e.estimate;
    best = std::min(best, sep[k]);
    swept = std::max(swept, e.swept);
    const double ratio = sep[k] / continuation_mae(r);
    const bool ok = ratio <= kSeparateRatio;
    char buf[200];
    std::snprintf(buf, sizeof buf, " %.4g (%.2f×)%s; whole %.4g (%.2f×); rest %.4g |", sep[k],
                  ratio, ok ? "" : " **>1.5×**", e.whole, e.whole / continuation_mae(r), e.rest);
    md += buf;
    if (!ok)
      check.fail(name + "/" + r.candidate.label + " separate",
                 figure(sep[k]) + " nm on the separate recording, " + figure(ratio) + "× the continuation's " +
                     figure(continuation_mae(r)) + " nm; whole history " + figure(e.whole / continuation_mae(r)) + "×");
  }
  double best_cont = INFINITY;
  for (const auto& r : sel.table)
    if (r.refused.empty() && !output_map_row(r)) best_cont = std::min(best_cont, continuation_mae(r));
  std::string both;
  for (std::size_t k = 0; k < std::min(analysis::default_candidates().size(), sel.table.size()); ++k)
    if (continuation_mae(sel.table[k]) <= kAutoMargin * best_cont && sep[k] <= kAutoMargin * best)
      both += (both.empty() ? "" : ", ") + sel.table[k].candidate.label;
  notes = "start window swept " + std::to_string(std::lround(100.0 * swept)) + " % of the training voltage range; auto's candidates within " +
          figure(100.0 * (kAutoMargin - 1.0)) + " % of the best kind on both recordings: " + (both.empty() ? "none" : both);
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
  for (const auto& c : analysis::default_candidates(kNeural))
    if (!output_map_label(c.label)) md += " " + c.label + " |", ++n;
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
  const SeparateRecording rec = separate_recording(stage, spec);
  const auto t0 = std::chrono::steady_clock::now();
  std::string notes;
  const std::string sep = separate_row(name, f, rec, spec.anchor_s, check, notes);
  const double run_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::printf("Separate recording (seed %llu, %.0f s simulated, from %.2f s on, start estimate over %.3g s, scored "
              "after it; %.1f s to run every kind): free-run MAE [nm] (× the continuation's); whole: the same model over the "
              "whole recording, its history known (the bound); rest: from rest without the estimate:\n\n%s%s\n",
              static_cast<unsigned long long>(separate_seed()), spec.duration_s, rec.cut_at_s, spec.anchor_s, run_s,
              separate_header().c_str(), sep.c_str());
  std::printf("%s: %s\n", name.c_str(), notes.c_str());
  check.report_passing(name);
}

INSTANTIATE_TEST_SUITE_P(Stages, StageMatrix, testing::ValuesIn(stage_names()),
                         [](const testing::TestParamInfo<std::string>& i) { return i.param; });
