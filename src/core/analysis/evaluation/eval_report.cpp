#include "piezo_compensation/analysis/evaluation/eval_report.h"

#include <algorithm>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/util/json_writer.h"

namespace piezo::analysis {

namespace {

std::string f1(double v) {
  if (!std::isfinite(v)) return "–";
  char b[32];
  std::snprintf(b, sizeof b, "%.1f", v);
  return b;
}
std::string f2(double v) {
  if (!std::isfinite(v)) return "–";
  char b[32];
  std::snprintf(b, sizeof b, "%.2f", v);
  return b;
}

void json_stats(util::JsonWriter& j, const ErrorStats& s) {
  j.begin_object();
  j.kv("mae_nm", s.mae_nm).kv("rms_nm", s.rms_nm).kv("max_nm", s.max_nm).kv("bias_nm", s.mean_nm).kv("samples", s.n);
  j.end_object();
}
void json_set(util::JsonWriter& j, const SetMetrics& s) {
  j.begin_object();
  for (const auto& [mode, m] : {std::pair<const char*, const ModeMetrics*>{"one_step", &s.one_step}, {"free_run", &s.free_run}}) {
    j.key(mode).begin_object();
    j.key("vs_measured");
    json_stats(j, m->vs_measured);
    j.key("vs_truth");
    if (m->vs_truth.valid()) json_stats(j, m->vs_truth);
    else j.null();
    j.end_object();
  }
  j.end_object();
}

void json_start(util::JsonWriter& j, const models::StartEstimate& st) {
  j.key("start_estimate").begin_object();
  j.kv("candidate", st.candidate).kv("candidates", st.candidates).kv("window_rows", st.window_rows);
  j.kv("offset_nm", st.offset_nm).kv("offset_sigma_nm", st.offset_sigma_nm);
  j.kv("window_rms_offset_only_nm", st.rms_rest_nm).kv("window_rms_nm", st.rms_nm);
  // The share of the voltage range the window swept (the memory of wider swings is not in it).
  j.kv("window_swept_v", st.window_swept_v).kv("voltage_range_v", st.range_v).kv("window_swept_fraction", st.swept_fraction());
  // The creep states fitted on the window (0 for a kind without linear states): each one's shift of the
  // prediction at the window's start [nm].
  j.kv("creep_states_fitted", st.linear_states).key("creep_state_shifts_nm").begin_array();
  for (double d : st.history.linear_shift_nm) j.value(d);
  j.end_array();
  j.end_object();
}

// What the anchor's start-up state estimate chose for each model (empty without an anchor).
std::string start_lines(const EvalContext& ctx, const std::vector<ModelEvaluation>& evals) {
  std::string s;
  if (ctx.anchor_s > 0)
    for (const auto& e : evals)
      s += "  - " + e.name + ", test: " + e.test.start.describe() +
           (ctx.creep_path.empty() ? std::string() : "; creep: " + e.creep_pred.start.describe()) + "\n";
  return s;
}

// The training recording's identification check each model file carries (`piezo fit`; docs/models.md).
std::string identification_lines(const std::vector<ModelEvaluation>& evals) {
  std::string s;
  for (const auto& e : evals) {
    if (!std::isfinite(e.carry_over_ratio)) continue;
    s += "- " + e.name + ": identification at fit " + f2(e.carry_over_ratio) + "x" +
         (e.carry_over_ratio > kCarryOverAdvised
              ? " (over " + f1(kCarryOverAdvised) + ": its training recording did not identify it; larger errors on "
                "new data than its validation figures may come from that)\n"
              : "\n");
  }
  return s;
}

std::ofstream open_out(const std::string& path) {
  std::ofstream f(path);
  if (!f) throw std::runtime_error(path + ": cannot open for writing");
  f.precision(10);
  return f;
}

// The report's sections, in the order eval_markdown writes them.
void zeroed_section(std::ostream& os, const EvalContext& ctx, const std::vector<ModelEvaluation>& evals, double floor) {
  if (std::any_of(evals.begin(), evals.end(), [](const ModelEvaluation& e) { return !e.zeroed.empty(); })) {
    os << "## Each recording's hold from a zero taken before it [nm]\n\nFree run from the recording's start; its offset "
          "from the readings over the " << f1(ctx.zero_window_s) << " s before the hold; walk: MAE over the "
       << f1(ctx.walk_end_s) << " s before the hold against the readings (floor " << f1(floor)
       << " nm); creep: the change from the hold's first to its last 5 s, predicted − measured.\n\n"
       << "| model | recording | hold [s] | offset | walk MAE | creep measured | creep predicted | creep error |\n"
       << "|---|---|---|---|---|---|---|---|\n";
    for (const auto& e : evals) {
      double walk = 0, worst = 0;
      for (const auto& z : e.zeroed) {
        os << "| " << e.name << " | " << z.recording << " | " << f1(z.hold_s) << " | " << f1(z.offset_nm) << " | "
           << f1(z.walk_mae_nm) << " | " << f1(z.creep_measured_nm) << " | " << f1(z.creep_predicted_nm) << " | "
           << f1(z.creep_error_nm()) << " |\n";
        walk += z.walk_mae_nm / static_cast<double>(e.zeroed.size());
        worst = std::max(worst, std::abs(z.creep_error_nm()));
      }
      if (!e.zeroed.empty())
        os << "| " << e.name << " | **mean / worst** | | | **" << f1(walk) << "** | | | **" << f1(worst) << "** |\n";
    }
    os << "\n";
  }
}

void all_modes_section(std::ostream& os, const std::vector<ModelEvaluation>& evals) {
  os << "## All modes [nm]: MAE / RMS / max\n\n"
     << "| model | set | one-step vs measured | one-step vs truth | free-run vs measured | free-run vs truth |\n"
     << "|---|---|---|---|---|---|\n";
  auto cell = [](const ErrorStats& s) { return s.valid() ? f1(s.mae_nm) + " / " + f1(s.rms_nm) + " / " + f1(s.max_nm) : std::string("–"); };
  for (const auto& e : evals)
    for (const auto& [set, m] : {std::pair<const char*, const SetMetrics*>{"hysteresis", &e.hysteresis}, {"creep", &e.creep}})
      os << "| " << e.name << " | " << set << " | " << cell(m->one_step.vs_measured) << " | " << cell(m->one_step.vs_truth)
         << " | " << cell(m->free_run.vs_measured) << " | " << cell(m->free_run.vs_truth) << " |\n";

}

void holds_section(std::ostream& os, const EvalContext& ctx, const std::vector<ModelEvaluation>& evals) {
  if (!evals.empty() && evals[0].holds_free_run.valid()) {
    os << "\n## Holds, free-run [nm]: MAE inside the holds, and the end-of-hold error (prediction − reference, "
          "means over each hold's last " << f1(ctx.final_window_s) << " s)\n\n"
       << "| model | hold MAE vs measured | hold MAE vs truth | end-of-hold error vs measured: max / mean abs | "
          "vs truth: max / mean abs | holds |\n|---|---|---|---|---|---|\n";
    auto endc = [](const HoldErrors& h) {
      return h.valid() ? f1(h.end_max_abs_nm) + " / " + f1(h.end_mean_abs_nm) : std::string("–");
    };
    for (const auto& e : evals)
      os << "| " << e.name << " | " << f1(e.holds_free_run.in_holds.mae_nm) << " | "
         << (e.holds_free_run_truth.valid() ? f1(e.holds_free_run_truth.in_holds.mae_nm) : std::string("–")) << " | "
         << endc(e.holds_free_run) << " | " << endc(e.holds_free_run_truth) << " | " << e.holds_free_run.end_error_nm.size()
         << " |\n";
  }
}

void finals_section(std::ostream& os, const EvalContext& ctx, const std::vector<ModelEvaluation>& evals) {
  if (!evals.empty() && !evals[0].finals.empty()) {
    os << "\n## Final position after each hold (mean of the last 5 s), deviation from the measurement [nm] (Fig. 14)\n\n"
       << "Encoder-noise band ±" << f1(ctx.noise_sigma_nm) << " nm (σ of one sample; the 5-s mean of the measurement itself "
       << "scatters less).\n\n| hold | segment |";
    for (const auto& e : evals) os << " " << e.name << " one-step | " << e.name << " free-run |";
    os << "\n|---|---|";
    for (std::size_t k = 0; k < evals.size(); ++k) os << "---|---|";
    os << "\n";
    for (std::size_t h = 0; h < evals[0].finals.size(); ++h) {
      os << "| " << h + 1 << " | " << evals[0].finals[h].segment << " |";
      for (const auto& e : evals) {
        const auto& f = e.finals[h];
        os << " " << f1(f.one_step_nm - f.measured_nm) << " | " << f1(f.free_run_nm - f.measured_nm) << " |";
      }
      os << "\n";
    }
    if (std::isfinite(evals[0].finals[0].truth_nm)) {
      os << "\n| model | mean abs final deviation vs truth, one-step | free-run | holds within the noise band (free-run vs truth) |\n|---|---|---|---|\n";
      for (const auto& e : evals) {
        double a = 0, b = 0;
        int within = 0;
        for (const auto& f : e.finals) {
          a += std::abs(f.one_step_nm - f.truth_nm);
          b += std::abs(f.free_run_nm - f.truth_nm);
          within += std::abs(f.free_run_nm - f.truth_nm) <= ctx.noise_sigma_nm;
        }
        os << "| " << e.name << " | " << f1(a / e.finals.size()) << " | " << f1(b / e.finals.size()) << " | " << within << "/"
           << e.finals.size() << " |\n";
      }
    }
  }
}

}  // namespace

std::string eval_markdown(const EvalContext& ctx, const std::vector<ModelEvaluation>& evals) {
  std::ostringstream os;
  const double floor = noise_floor_mae_nm(ctx.noise_sigma_nm);
  os << "# Model evaluation\n\n"
     << "- test data: `" << ctx.test_path << "` (hysteresis: samples outside creep holds"
     << (ctx.warmup_s > 0 ? ", after a " + f1(ctx.warmup_s) + " s warm-up" : std::string()) << ")\n"
     << "- creep data: `" << (ctx.creep_path.empty() ? ctx.test_path + " (its holds)" : ctx.creep_path)
     << "` (creep: samples in holds, phase = hold)\n- axis " << ctx.axis << "\n"
     << (ctx.anchor_s > 0 ? std::string(ctx.anchor_history ? "- initial state and offset: estimated" : "- initial offset: "
                                "anchored") + " on the first " + f1(ctx.anchor_s) + " s of measured position (scored after them)\n"
                          : std::string("- initial state: at rest at the first voltage and measured position (no anchor)\n"));
  os << start_lines(ctx, evals) << identification_lines(evals);
  auto seglist = [](const std::vector<int>& v) {
    std::string s;
    for (int k : v) s += (s.empty() ? "" : ",") + std::to_string(k);
    return s;
  };
  if (!ctx.test_segments.empty() || !ctx.creep_segments.empty())
    os << "- one continuous recording, models run over all of it; scored segments: hysteresis "
       << (ctx.test_segments.empty() ? std::string("all") : seglist(ctx.test_segments)) << ", creep "
       << (ctx.creep_segments.empty() ? std::string("all") : seglist(ctx.creep_segments)) << "\n";
  os
     << "- encoder noise σ = " << f2(ctx.noise_sigma_nm) << " nm → noise floor for MAE against the measurement: σ·√(2/π) = **"
     << f1(floor) << " nm** (a perfect predictor scores this against raw encoder samples)";
  if (std::isfinite(ctx.measured_sigma_nm)) os << "; σ measured from measured − truth on the test data: " << f2(ctx.measured_sigma_nm) << " nm";
  os << "\n\nOne-step: the measured position of each sample is fed back (as in the study). Free-run: the model's own "
        "predictions are fed back (no sensor). Models without position features give the same numbers in both.\n\n";

  os << "## Table 3 (study layout): MAE [nm]\n\n| model | kind | hysteresis MAE | creep MAE | noise floor |\n|---|---|---|---|---|\n";
  for (const auto& e : evals)
    os << "| " << e.name << " | " << e.kind << " | " << f1(e.hysteresis.one_step.vs_measured.mae_nm) << " | "
       << f1(e.creep.one_step.vs_measured.mae_nm) << " | " << f1(floor) << " |\n";
  os << "\n(one-step, against the measurement — the study's setting; the study reported 8.2 nm / 10.0 nm for linear "
        "regression, below this floor, see docs/models.md.)\n\n";

  zeroed_section(os, ctx, evals, floor);
  all_modes_section(os, evals);
  holds_section(os, ctx, evals);
  finals_section(os, ctx, evals);
  os << "\n## Plots\n\n![Table 3](table3.png)\n\n![Final positions](final_positions.png)\n\n"
     << "![Hysteresis traces](traces_hysteresis.png)\n\n![Creep traces](traces_creep.png)\n";
  for (const auto& n : ctx.lasso_notes) os << "\n" << n << "\n";
  return os.str();
}

void write_eval_report(const std::string& dir, const EvalContext& ctx, const std::vector<ModelEvaluation>& evals,
                       const io::Dataset& test, const io::Dataset* creep) {
  {
    auto md = open_out(dir + "/report.md");
    md << eval_markdown(ctx, evals);
  }
  {
    auto js = open_out(dir + "/report.json");
    util::JsonWriter j(js);
    j.begin_object();
    j.kv("test_data", ctx.test_path).kv("creep_data", ctx.creep_path).kv("axis", ctx.axis);
    j.kv("noise_sigma_nm", ctx.noise_sigma_nm).kv("noise_floor_mae_nm", noise_floor_mae_nm(ctx.noise_sigma_nm));
    j.kv("measured_sigma_nm", ctx.measured_sigma_nm).kv("warmup_s", ctx.warmup_s).kv("anchor_s", ctx.anchor_s);
    j.kv("anchor_history", ctx.anchor_history);
    j.key("models").begin_array();
    for (const auto& e : evals) {
      j.begin_object();
      j.kv("name", e.name).kv("kind", e.kind).kv("num_parameters", e.num_parameters).kv("uses_positions", e.uses_positions);
      j.kv("carry_over_ratio", e.carry_over_ratio);  // from the model file (null when it has none)
      if (ctx.anchor_s > 0) json_start(j, e.test.start);
      j.key("hysteresis");
      json_set(j, e.hysteresis);
      j.key("creep");
      json_set(j, e.creep);
      auto json_holds = [&](const char* k, const HoldErrors& h) {
        j.key(k).begin_object();
        j.kv("mae_nm", h.in_holds.mae_nm).kv("end_max_abs_nm", h.end_max_abs_nm).kv("end_mean_abs_nm", h.end_mean_abs_nm);
        j.key("end_error_nm").array(h.end_error_nm);
        j.end_object();
      };
      json_holds("holds_free_run_vs_measured", e.holds_free_run);
      json_holds("holds_free_run_vs_truth", e.holds_free_run_truth);
      j.key("final_positions").begin_array();
      for (const auto& f : e.finals) {
        j.begin_object();
        j.kv("segment", f.segment).kv("hold_s", f.hold_s).kv("measured_nm", f.measured_nm).kv("truth_nm", f.truth_nm);
        j.kv("one_step_nm", f.one_step_nm).kv("free_run_nm", f.free_run_nm);
        j.end_object();
      }
      j.end_array();
      j.end_object();
    }
    j.end_array();
    j.end_object();
    js << "\n";
  }
  // Traces for the plots: a window of the hysteresis test data, and every hold of the creep data.
  auto write_traces = [&](const std::string& path, const io::Dataset& d, bool creep_set, std::size_t b, std::size_t e,
                          std::size_t stride, const std::vector<char>* mask) {
    auto f = open_out(path);
    const io::AxisSeries& ax = d.axis(ctx.axis);
    f << "time_s,segment,voltage_v,measured_nm,truth_nm";
    for (const auto& ev : evals) f << "," << ev.name << ":one_step," << ev.name << ":free_run";
    f << "\n";
    for (std::size_t i = b; i < e; i += stride) {
      if (mask && !(*mask)[i]) continue;
      f << d.time_s[i] << "," << (d.segment.empty() ? -1 : d.segment[i]) << "," << ax.voltage_v[i] << "," << ax.position_nm[i]
        << "," << (ax.has_truth() ? ax.true_position_nm[i] : NAN);
      for (const auto& ev : evals) {
        const SeriesPrediction& p = creep_set ? ev.creep_pred : ev.test;
        f << "," << p.one_step[i] << "," << p.free_run[i];
      }
      f << "\n";
    }
  };
  const std::vector<char> hm = hysteresis_mask(test, ctx.warmup_s, ctx.test_segments);
  std::size_t start = 0;  // a 20-min window from the middle of the scored hysteresis samples
  std::vector<std::size_t> scored;
  for (std::size_t i = 0; i < hm.size(); ++i)
    if (hm[i]) scored.push_back(i);
  if (!scored.empty()) start = scored[scored.size() / 2];
  const std::size_t win = test.size() > 1 ? static_cast<std::size_t>(1200 * test.sample_rate_hz()) : 1;
  write_traces(dir + "/traces_test.csv", test, false, start, std::min(test.size(), start + win), 1, nullptr);
  const io::Dataset& cd = creep ? *creep : test;
  const std::vector<char> cm = hold_mask(cd, ctx.creep_segments);
  std::size_t holds = 0;
  for (char c : cm) holds += c;
  write_traces(dir + "/traces_creep.csv", cd, true, 0, cd.size(), std::max<std::size_t>(1, holds / 100000), &cm);
}

}  // namespace piezo::analysis
