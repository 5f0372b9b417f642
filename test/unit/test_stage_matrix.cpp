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
std::string start_state(const char* figure) {
  return std::string(figure) + " (separate nm, × the continuation nm): the start estimate fits a constant offset "
         "over its window while the hysteresis state is still wrong, and keeps it after the state converged "
         "(issue 26 item 1)";
}
const std::map<std::string, std::string> kKnownFailing = {
    {"lowvolt_pi_creep/dense separate", start_state("3429, 14.44× 237.5")},  // after the estimate's third background (8efef26)
    {"lowvolt_preisach/linear (lasso features) separate", start_state("2039, 2.794× 729.9")},  // after the estimate's third background (8efef26)
    {"lowvolt_preisach_creep/linear (lasso features) separate", start_state("2164, 2.323× 931.7")},  // after the estimate's third background (8efef26)
    {"mm3e_preisach/linear (lasso features) separate", start_state("60.26, 2.805× 21.48")},  // after the estimate's third background (8efef26)
    {"mm3e_preisach/pi_creep_lti separate", start_state("103.5, 2.305× 44.91")},  // after the estimate's third background (8efef26)
    {"mm3e_preisach/pi_creep_prony separate", start_state("103.4, 2.314× 44.68")},  // after the estimate's third background (8efef26)
    {"mm3e_preisach_creep/linear (lasso features) separate", start_state("93.56, 4.063× 23.02")},  // after the estimate's third background (8efef26)
    {"mm3e_preisach_creep/pi_creep_log separate", start_state("90.78, 2.111× 43.01")},  // after the estimate's third background (8efef26)
    {"mm3e_preisach_creep/pi_creep_lti separate", start_state("98.05, 2.225× 44.07")},  // after the estimate's third background (8efef26)
    {"mm3e_preisach_creep/pi_creep_prony separate", start_state("97.91, 2.158× 45.37")},  // after the estimate's third background (8efef26)
    {"lowvolt_pi/auto", "auto chose pi: 42.84 nm, best kind 38.27 nm; pi is within the paired-block noise of preisach on the 10-s tail and has fewer parameters"},
    {"lowvolt_pi/linear (lasso features) separate", start_state("1.401e+04, 73.48× 190.7")},
    {"lowvolt_pi/pi separate", start_state("281.8, 6.578× 42.84")},
    {"lowvolt_pi/pi_creep_fractional separate", start_state("385, 3.813× 101")},
    {"lowvolt_pi/pi_creep_log separate", start_state("397.5, 3.735× 106.4")},
    {"lowvolt_pi/pi_creep_lti separate", start_state("380, 3.829× 99.25")},
    {"lowvolt_pi/pi_creep_prony separate", start_state("380, 3.828× 99.25")},
    {"lowvolt_pi/preisach separate", start_state("278.5, 7.278× 38.27")},
    {"lowvolt_pi/preisach_creep_prony separate", start_state("259.3, 6.037× 42.96")},
    {"lowvolt_pi/kan separate", start_state("632.4, 7.437× 85.04")},
    {"lowvolt_pi/dense separate", start_state("382.4, 3.729× 102.5")},
    {"lowvolt_pi/lstm separate", start_state("4606, 2.292× 2009")},
    {"lowvolt_pi_creep/linear (lasso features) separate", start_state("1155, 4.207× 274.5")},
    {"lowvolt_pi_creep/pi separate", start_state("1949, 11.97× 162.8")},
    {"lowvolt_pi_creep/pi_creep_fractional separate", start_state("630.6, 5.79× 108.9")},
    {"lowvolt_pi_creep/pi_creep_log separate", start_state("920.3, 5.962× 154.4")},
    {"lowvolt_pi_creep/pi_creep_lti separate", start_state("674.3, 3.26× 206.8")},
    {"lowvolt_pi_creep/pi_creep_prony separate", start_state("659, 3.657× 180.2")},
    {"lowvolt_pi_creep/preisach separate", start_state("2176, 13.14× 165.5")},
    {"lowvolt_pi_creep/preisach_creep_prony separate", start_state("813.5, 9.181× 88.6")},
    {"lowvolt_pi_creep/kan separate", start_state("269.9, 4.212× 64.08")},
    {"lowvolt_pi_creep/lstm separate", start_state("5157, 2.457× 2099")},
    {"lowvolt_preisach/pi separate", start_state("4725, 4.8× 984.4")},
    {"lowvolt_preisach/pi_creep_fractional separate", start_state("4343, 5.16× 841.6")},
    {"lowvolt_preisach/pi_creep_log separate", start_state("4478, 5.266× 850.4")},
    {"lowvolt_preisach/pi_creep_lti separate", start_state("4113, 5.316× 773.8")},
    {"lowvolt_preisach/pi_creep_prony separate", start_state("4157, 5.177× 803.1")},
    {"lowvolt_preisach/kan separate", start_state("3320, 9.516× 348.9")},
    {"lowvolt_preisach/dense separate", start_state("528.1, 1.745× 302.7")},
    {"lowvolt_preisach/lstm separate", start_state("6255, 3.829× 1633")},
    {"lowvolt_preisach_creep/pi separate", start_state("5911, 5.268× 1122")},
    {"lowvolt_preisach_creep/pi_creep_fractional separate", start_state("4995, 5.539× 901.8")},
    {"lowvolt_preisach_creep/pi_creep_log separate", start_state("4949, 5.78× 856.2")},
    {"lowvolt_preisach_creep/pi_creep_lti separate", start_state("4953, 5.584× 887")},
    {"lowvolt_preisach_creep/pi_creep_prony separate", start_state("4991, 5.534× 901.9")},
    {"lowvolt_preisach_creep/preisach separate", start_state("2992, 6.959× 429.9")},
    {"lowvolt_preisach_creep/preisach_creep_prony separate", start_state("776.8, 2.302× 337.4")},
    {"lowvolt_preisach_creep/kan separate", start_state("3205, 6.325× 506.7")},
    {"lowvolt_preisach_creep/dense separate", start_state("771.3, 2.12× 363.9")},
    {"lowvolt_preisach_creep/lstm separate", start_state("6893, 3.92× 1758")},
    {"stack150_pi/linear (lasso features) separate", start_state("5.09e+07, 3.76e+05× 135.4")},
    {"stack150_pi/pi separate", start_state("183.9, 10.19× 18.05")},
    {"stack150_pi/pi_creep_fractional separate", start_state("179.6, 8.804× 20.4")},
    {"stack150_pi/pi_creep_log separate", start_state("180.5, 9.46× 19.08")},
    {"stack150_pi/pi_creep_lti separate", start_state("184.5, 10.43× 17.69")},
    {"stack150_pi/pi_creep_prony separate", start_state("184.1, 10.24× 17.97")},
    {"stack150_pi/preisach separate", start_state("235, 95.94× 2.45")},
    {"stack150_pi/preisach_creep_prony separate", start_state("235.4, 95.98× 2.453")},
    {"stack150_pi/kan separate", start_state("199.4, 3.709× 53.76")},
    {"stack150_pi/dense separate", start_state("191.7, 7.251× 26.43")},
    {"stack150_pi/lstm separate", start_state("1532, 2.371× 646")},
    {"stack150_pi/auto separate", "auto chose preisach: 235 nm on the separate recording, best kind 179.6 nm; no kind auto offers starts near its continuation with the offset estimate"},
    {"stack150_pi_creep/linear (lasso features) separate", start_state("6.758e+07, 4.367e+05× 154.8")},
    {"stack150_pi_creep/pi separate", start_state("206.3, 2.103× 98.12")},
    {"stack150_pi_creep/pi_creep_fractional separate", start_state("353.7, 16.29× 21.71")},
    {"stack150_pi_creep/pi_creep_log separate", start_state("353.3, 12.54× 28.18")},
    {"stack150_pi_creep/pi_creep_lti separate", start_state("355.6, 20.7× 17.18")},
    {"stack150_pi_creep/pi_creep_prony separate", start_state("365.7, 16.62× 22")},
    {"stack150_pi_creep/preisach separate", start_state("190.3, 2.076× 91.66")},
    {"stack150_pi_creep/preisach_creep_prony separate", start_state("408.6, 25.21× 16.21")},
    {"stack150_pi_creep/kan separate", start_state("180.4, 2.35× 76.75")},
    {"stack150_pi_creep/dense separate", start_state("337.9, 12.75× 26.5")},
    {"stack150_pi_creep/lstm separate", start_state("1544, 2.27× 680.1")},
    {"stack150_pi_creep/auto separate", "auto chose pi_creep_lti: 355.6 nm on the separate recording, best kind 180.4 nm; no kind auto offers starts near its continuation with the offset estimate"},
    {"stack150_preisach/linear (lasso features) separate", start_state("491, 2.521× 194.8")},
    {"stack150_preisach/preisach separate", start_state("133.6, 5.788× 23.07")},
    {"stack150_preisach/preisach_creep_prony separate", start_state("160.7, 7.823× 20.54")},
    {"stack150_preisach/kan separate", start_state("495.9, 3.331× 148.9")},
    {"stack150_preisach/dense separate", start_state("237, 2.004× 118.2")},
    {"stack150_preisach/lstm separate", start_state("1325, 1.881× 704.6")},
    {"stack150_preisach/auto separate", "auto chose preisach_creep_prony: 160.7 nm on the separate recording, best kind 133.6 nm; no kind auto offers starts near its continuation with the offset estimate"},
    {"stack150_preisach_creep/linear (lasso features) separate", start_state("696.8, 3.474× 200.6")},
    {"stack150_preisach_creep/pi_creep_lti separate", start_state("550.2, 1.677× 328.2")},
    {"stack150_preisach_creep/pi_creep_prony separate", start_state("550.4, 1.682× 327.2")},
    {"stack150_preisach_creep/preisach_creep_prony separate", start_state("334.2, 10.82× 30.89")},
    {"stack150_preisach_creep/kan separate", start_state("321.5, 1.551× 207.3")},
    {"stack150_preisach_creep/dense separate", start_state("361.2, 2.96× 122")},
    {"stack150_preisach_creep/lstm separate", start_state("1360, 1.818× 748")},
    {"stack150_preisach_creep/auto separate", "auto chose preisach_creep_prony: 334.2 nm on the separate recording, best kind 126.2 nm; no kind auto offers starts near its continuation with the offset estimate"},
    {"mm3e_pi/linear (lasso features) separate", start_state("26.18, 1.534× 17.06")},
    {"mm3e_pi/pi separate", start_state("31.78, 1.942× 16.36")},
    {"mm3e_pi/pi_creep_fractional separate", start_state("30.9, 1.886× 16.38")},
    {"mm3e_pi/pi_creep_log separate", start_state("30.77, 1.879× 16.37")},
    {"mm3e_pi/pi_creep_lti separate", start_state("30.84, 1.882× 16.38")},
    {"mm3e_pi/pi_creep_prony separate", start_state("31.03, 1.897× 16.36")},
    {"mm3e_pi/preisach separate", start_state("38.37, 2.337× 16.42")},
    {"mm3e_pi/preisach_creep_prony separate", start_state("38.76, 2.364× 16.39")},
    {"mm3e_pi/dense separate", start_state("30.63, 1.826× 16.77")},
    {"mm3e_pi/lstm separate", start_state("250.7, 12.33× 20.34")},
    {"mm3e_pi/auto separate", "auto chose pi_creep_lti: 30.84 nm on the separate recording, best kind 18.41 nm; no kind auto offers starts near its continuation with the offset estimate"},
    {"mm3e_pi_creep/linear (lasso features) separate", start_state("73.14, 4.123× 17.74")},
    {"mm3e_pi_creep/pi separate", start_state("155.2, 5.511× 28.16")},
    {"mm3e_pi_creep/pi_creep_fractional separate", start_state("83.95, 4.934× 17.02")},
    {"mm3e_pi_creep/pi_creep_log separate", start_state("81.7, 4.705× 17.36")},
    {"mm3e_pi_creep/pi_creep_lti separate", start_state("78.98, 4.643× 17.01")},
    {"mm3e_pi_creep/pi_creep_prony separate", start_state("81.68, 4.81× 16.98")},
    {"mm3e_pi_creep/preisach separate", start_state("140, 5.096× 27.48")},
    {"mm3e_pi_creep/preisach_creep_prony separate", start_state("89.8, 5.335× 16.83")},
    {"mm3e_pi_creep/kan separate", start_state("31.34, 1.783× 17.58")},
    {"mm3e_pi_creep/dense separate", start_state("60.35, 3.51× 17.19")},
    {"mm3e_pi_creep/lstm separate", start_state("276.6, 12.37× 22.36")},
    {"mm3e_pi_creep/auto separate", "auto chose preisach_creep_prony: 89.8 nm on the separate recording, best kind 31.34 nm; no kind auto offers starts near its continuation with the offset estimate"},
    {"mm3e_preisach/pi_creep_fractional separate", start_state("94.62, 2.833× 33.4")},
    {"mm3e_preisach/pi_creep_log separate", start_state("80.22, 2.027× 39.57")},
    {"mm3e_preisach/kan separate", start_state("119.4, 6.624× 18.02")},
    {"mm3e_preisach/dense separate", start_state("105.7, 5.553× 19.03")},
    {"mm3e_preisach/lstm separate", start_state("284, 14.05× 20.21")},
    {"mm3e_preisach/auto separate", "auto chose kan: 119.4 nm on the separate recording, best kind 17.64 nm; kan leads on holds and hold ends of the tail and generalises worse"},
    {"mm3e_preisach_creep/pi separate", start_state("68.37, 2.471× 27.67")},
    {"mm3e_preisach_creep/pi_creep_fractional separate", start_state("65.83, 1.709× 38.52")},
    {"mm3e_preisach_creep/preisach separate", start_state("130.9, 3.954× 33.1")},
    {"mm3e_preisach_creep/preisach_creep_prony separate", start_state("69.2, 3.937× 17.58")},
    {"mm3e_preisach_creep/kan separate", start_state("113.7, 6.124× 18.57")},
    {"mm3e_preisach_creep/dense separate", start_state("98.61, 4.635× 21.27")},
    {"mm3e_preisach_creep/lstm separate", start_state("305.5, 11.38× 26.83")},
    {"mm3e_preisach_creep/auto separate", "auto chose preisach_creep_prony: 69.2 nm on the separate recording, best kind 25.66 nm; no kind auto offers starts near its continuation with the offset estimate"},
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
