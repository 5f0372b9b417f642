#include "piezo_compensation/analysis/residual/residual_report.h"

#include <cmath>
#include <fstream>
#include <iomanip>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/analysis/evaluation/evaluation.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/util/json_writer.h"
#include "piezo_compensation/util/format.h"

namespace piezo::analysis {

namespace {

std::string num(double v) { return std::isfinite(v) ? util::fmt(v, 4) : "–"; }

std::ofstream open_out(const std::string& path) {
  std::ofstream f(path);
  if (!f) throw std::runtime_error(path + ": cannot open for writing");
  f << std::setprecision(10);
  return f;
}

std::string params_text(const std::map<std::string, double>& p, const std::map<std::string, std::string>& l) {
  std::ostringstream os;
  bool first = true;
  for (const auto& [k, v] : l) {
    os << (first ? "" : ", ") << k << " = " << v;
    first = false;
  }
  for (const auto& [k, v] : p) {
    os << (first ? "" : ", ") << k << " = " << std::setprecision(4) << v;
    first = false;
  }
  return os.str();
}

// The first term of each effect (terms are stored in the order the effects were added).
std::vector<std::size_t> first_terms(const models::AugmentedModel& m, const ResidualResult& res) {
  std::vector<std::size_t> out;
  std::size_t term = 0;
  for (const auto& e : res.effects) {
    while (term < m.terms().size() && m.terms()[term].family != e.family) ++term;
    out.push_back(term);
    ++term;
  }
  return out;
}

// The explaining variable of an effect on TEST: the signal its term reads after lag/low-pass, a phase within
// the period for periodic terms. `data` may be TRAIN+TEST joined (warm start): only its last `keep` rows.
std::vector<double> explaining_variable(const models::AugmentedModel& m, std::size_t term_index, const io::Dataset& data,
                                        const std::string& axis, PredictionMode mode, std::size_t keep) {
  const std::vector<models::EffectTerm>& all = m.terms();
  const models::EffectTerm target = all[term_index];
  models::EffectTermStream stream(all, data.sample_rate_hz(), m.offset_nm());
  models::InputResolver cols(data, stream.column_signals(), axis);
  models::ModelPtr base = m.base().clone();
  models::StreamOptions so;
  so.mode = mode;
  const std::vector<double> xb = models::stream_model(*base, data, axis, so).prediction;
  const auto& ax = data.axis(axis);
  std::size_t first = 0;
  for (std::size_t i = 0; i < term_index; ++i) first += all[i].num_regressors();
  std::vector<double> out(data.size()), buf(stream.num_regressors()), colv(std::max<std::size_t>(1, cols.size()));
  for (std::size_t i = 0; i < data.size(); ++i) {
    cols.fill(i, colv.data());
    stream.raw_and_commit(ax.voltage_v[i], xb[i], colv.data(), buf.data());
    const double* z = buf.data() + first;
    if (target.kind() == models::TermKind::kSinCos) {
      double ph = std::atan2(z[0], z[1]) / 6.283185307179586;
      if (ph < 0) ph += 1.0;
      out[i] = ph * target.period;
    } else if (target.kind() == models::TermKind::kPowers) {
      out[i] = std::cbrt(z[1]) * target.pre_scale + target.pre_center;
    } else if (target.is_gain()) {
      const double q = target.scales == models::kSignalVoltage ? ax.voltage_v[i] : xb[i];
      out[i] = q != target.reference ? z[0] / (q - target.reference) * target.pre_scale + target.pre_center : NAN;
    } else {
      out[i] = z[0];
    }
  }
  return std::vector<double>(out.end() - static_cast<long>(keep), out.end());
}

std::string explaining_label(const models::EffectTerm& t) {
  if (t.kind() == models::TermKind::kSinCos) return t.signal == models::kSignalTime ? "time within period [s]" : "position within period [nm]";
  if (t.kind() == models::TermKind::kRate) return "voltage step (low-passed) [V]";
  std::string s = t.signal == models::kSignalVoltage ? "voltage [V]" : t.signal == models::kSignalPosition ? "predicted position [nm]" : t.signal;
  if (t.kind() == models::TermKind::kPlay) s = "play(" + s + ")";
  if (t.lag_s > 0) s += ", lag " + num(t.lag_s) + " s";
  if (t.time_constant_s > 0) s += ", low-pass " + num(t.time_constant_s) + " s";
  if (t.is_gain()) s = "gain signal " + s + " (scales the " + (t.scales == models::kSignalVoltage ? "voltage" : "output") + ")";
  return s;
}

struct HoldSummary {
  HoldErrors before, after, before_truth, after_truth;
};

void json_stats(util::JsonWriter& j, const ErrorStats& e) {
  j.begin_object().kv("mae_nm", e.mae_nm).kv("rms_nm", e.rms_nm).kv("max_nm", e.max_nm).kv("n", e.n).end_object();
}
void json_holds(util::JsonWriter& j, const HoldErrors& h) {
  j.begin_object().kv("mae_nm", h.in_holds.mae_nm).kv("end_max_abs_nm", h.end_max_abs_nm).kv("end_mean_abs_nm", h.end_mean_abs_nm);
  j.key("end_error_nm").array(h.end_error_nm);
  j.end_object();
}
void json_score(util::JsonWriter& j, const FamilyScore& s) {
  j.begin_object().kv("family", s.family).kv("available", s.available).kv("explained_variance", s.explained_variance);
  j.kv("p_value", s.p_value).kv("significant", s.significant).kv("validation_gain", s.validation_gain);
  j.kv("hold_validation_gain", s.hold_validation_gain).kv("parameters", s.parameters).kv("variants", s.variants);
  j.kv("validation_gain_first_half", s.validation_gain_halves.first).kv("validation_gain_second_half", s.validation_gain_halves.second);
  j.kv("removed_fraction", s.removed_fraction).kv("removed_nm", s.removed_nm).kv("systematic_nm", s.systematic_nm);
  j.kv("clearly_better", s.clearly_better);
  j.kv("operating_point", is_operating_point_family(s.family)).kv("verdict", s.verdict).kv("note", s.note);
  j.key("labels").begin_object();
  for (const auto& [k, v] : s.best.labels) j.kv(k, v);
  j.end_object().end_object();
}

}  // namespace

std::string residual_summary(const ResidualResult& res) {
  std::ostringstream os;
  os << "TEST MAE " << num(res.before_test.mae_nm) << " nm → " << num(res.after_test.mae_nm) << " nm with "
     << res.effects.size() << " effect(s):";
  for (const auto& e : res.effects) os << " " << e.family;
  if (res.remainder.explained)
    os << "; what is left is at the noise floor (σ " << num(res.remainder.noise_sigma_nm) << " nm from the data)";
  else
    os << "; NOT EXPLAINED: " << num(res.remainder.structure_nm) << " nm of slow structure above the noise floor (σ "
       << num(res.remainder.noise_sigma_nm) << " nm)"
       << (res.remainder.correlates.empty() ? "" : ", top correlate " + res.remainder.correlates.front().first);
  for (std::size_t k = 0; k < res.remainder.steps.size(); ++k)
    os << (k ? ", " : "; steps ") << num(res.remainder.steps[k].size_nm) << " nm at t = " << num(res.remainder.steps[k].time_s) << " s";
  return os.str();
}

namespace {

// What the report's parts share.
struct ReportParts {
  const ResidualReportContext& ctx;
  const ResidualResult& res;
  const io::Dataset& train;
  const io::Dataset& test;
  const models::AugmentedModel& aug;
  std::vector<std::size_t> firsts;  // first term of each effect in the augmented model
  HoldSummary hs;
  bool truth = false, holds = false;
};

void write_predictions(const std::string& dir, const ReportParts& p) {
  const ResidualResult& res = p.res;
  const io::Dataset& test = p.test;
  const auto& meas = test.axis(p.ctx.axis).position_nm;
  auto f = open_out(dir + "/predictions.csv");
  f << "time_s,measured_nm,predicted_before_nm,predicted_after_nm\n";
  for (std::size_t i = 0; i < test.size(); ++i)
    f << test.time_s[i] << "," << meas[i] << "," << res.test_pred_before[i] << "," << res.test_pred_after[i] << "\n";
}

void write_explain(const std::string& dir, const ReportParts& p, PredictionMode mode) {
  const ResidualResult& res = p.res;
  const io::Dataset &train = p.train, &test = p.test;
  const std::string& axis = p.ctx.axis;
  const auto& meas = test.axis(axis).position_nm;
  const auto& aug = p.aug;
  const auto& firsts = p.firsts;
  io::Dataset stream_data = test;  // what the explaining variables are streamed over
  if (res.warm_started) {
    stream_data = train;
    stream_data.append(test);
  }
  std::vector<std::vector<double>> ev;
  std::vector<std::string> names;
  for (std::size_t e = 0; e < res.effects.size(); ++e) {
    if (firsts[e] >= aug.terms().size()) break;
    ev.push_back(explaining_variable(aug, firsts[e], stream_data, axis, mode, test.size()));
    names.push_back("effect" + std::to_string(e + 1) + "_" + res.effects[e].family);
  }
  auto f = open_out(dir + "/explain.csv");
  f << "time_s,residual_before_nm,residual_after_nm";
  for (std::size_t e = 0; e < res.effects.size(); ++e) f << ",residual_step" << e + 1 << "_nm";
  for (const auto& n : names) f << "," << n;
  f << "\n";
  for (std::size_t i = 0; i < test.size(); ++i) {
    f << test.time_s[i] << "," << meas[i] - res.test_pred_before[i] << "," << meas[i] - res.test_pred_after[i];
    for (const auto& e : res.effects) f << "," << meas[i] - e.test_prediction[i];
    for (const auto& v : ev) f << "," << v[i];
    f << "\n";
  }
}

void json_effects(util::JsonWriter& j, const ReportParts& p) {
  const ResidualResult& res = p.res;
  const auto& aug = p.aug;
  const auto& firsts = p.firsts;
  j.key("effects").begin_array();
  for (std::size_t i = 0; i < res.effects.size(); ++i) {
    const auto& e = res.effects[i];
    j.begin_object().kv("family", e.family).kv("gain", is_gain_family(e.family));
    j.kv("acts_on", e.in_readings ? "readings" : "position");
    j.key("parameters").begin_object();
    for (const auto& [k, v] : e.labels) j.kv(k, v);
    for (const auto& [k, v] : e.parameters) j.kv(k, v);
    j.end_object();
    j.kv("explained_variance", e.explained_variance).kv("p_value", e.p_value).kv("validation_gain", e.validation_gain);
    j.kv("hold_validation_gain", e.hold_validation_gain);
    j.kv("explaining_variable", firsts[i] < aug.terms().size() ? explaining_label(aug.terms()[firsts[i]]) : "?");
    j.key("test_after");
    json_stats(j, e.test_after);
    j.key("competitors").begin_array();
    for (const auto& c : e.competitors) json_score(j, c);
    j.end_array().end_object();
  }
  j.end_array();
}

void json_remainder(util::JsonWriter& j, const ResidualResult& res) {
  j.key("steps_test_mae_nm").begin_array().value(res.before_test.mae_nm);
  for (const auto& e : res.effects) j.value(e.test_after.mae_nm);
  j.end_array();
  j.key("final_ranking").begin_array();
  for (const auto& s : res.final_ranking) json_score(j, s);
  j.end_array();
  const Remainder& r = res.remainder;
  j.key("remainder").begin_object().kv("explained", r.explained).kv("noise_sigma_nm", r.noise_sigma_nm);
  j.kv("noise_floor_mae_nm", noise_floor_mae_nm(r.noise_sigma_nm)).kv("noise_floor", r.noise_floor);
  j.kv("structure_nm", r.structure_nm);
  j.kv("p_value", r.p_value).kv("block_s", r.block_s).kv("blocks", r.blocks);
  j.key("correlates").begin_array();
  for (std::size_t k = 0; k < r.correlates.size() && k < 8; ++k)
    j.begin_object().kv("signal", r.correlates[k].first).kv("correlation", r.correlates[k].second).end_object();
  j.end_array();
  j.key("steps").begin_array();
  for (const auto& st : r.steps) j.begin_object().kv("time_s", st.time_s).kv("size_nm", st.size_nm).kv("z", st.z).end_object();
  j.end_array().end_object();
}

void write_json(const std::string& dir, const ReportParts& p) {
  const ResidualResult& res = p.res;
  const ResidualReportContext& ctx = p.ctx;
  const std::string& axis = ctx.axis;
  const io::Dataset &train = p.train, &test = p.test;
  const HoldSummary& hs = p.hs;
  const bool truth = p.truth, holds = p.holds;
  auto f = open_out(dir + "/report.json");
  util::JsonWriter j(f);
  j.begin_object().kv("axis", axis).kv("mode", ctx.mode).kv("base_model", ctx.base_kind).kv("base_choice", ctx.base_choice);
  j.kv("train_rows", train.size()).kv("test_rows", test.size()).kv("warm_start", res.warm_started);
  j.kv("anchor_s", res.anchor_s).kv("test_first_scored_row", res.test_first_scored);
  const std::pair<const char*, const ErrorStats*> stats[] = {
      {"before", &res.before_test}, {"after", &res.after_test}, {"before_vs_truth", &res.before_test_truth},
      {"after_vs_truth", &res.after_test_truth}};
  const std::pair<const char*, const HoldErrors*> hold_stats[] = {
      {"before", &hs.before}, {"after", &hs.after}, {"before_vs_truth", &hs.before_truth}, {"after_vs_truth", &hs.after_truth}};
  for (std::size_t k = 0; k < (truth ? 4u : 2u); ++k) {
    j.key(stats[k].first);
    json_stats(j, *stats[k].second);
  }
  if (holds) {
    j.key("holds").begin_object();
    for (std::size_t k = 0; k < (truth ? 4u : 2u); ++k) {
      j.key(hold_stats[k].first);
      json_holds(j, *hold_stats[k].second);
    }
    j.end_object();
  }
  json_effects(j, p);
  json_remainder(j, res);
  j.end_object();
  f << "\n";
}

void md_header(std::ostream& f, const ReportParts& p) {
  const ResidualResult& res = p.res;
  const ResidualReportContext& ctx = p.ctx;
  const std::string& axis = ctx.axis;
  const io::Dataset &train = p.train, &test = p.test;
  const bool truth = p.truth;
  f << std::setprecision(4);
  f << "# Residual report: axis " << axis << ", base model `" << ctx.base_kind << "`, " << ctx.mode << "\n\n";
  if (!ctx.base_choice.empty()) f << "Base: " << ctx.base_choice << ".\n\n";
  f << "TRAIN " << train.size() << " rows (" << (train.source.empty() ? "?" : train.source) << "), TEST " << test.size()
    << " rows (" << (test.source.empty() ? "?" : test.source) << "), " << train.sample_rate_hz() << " Hz. "
    << (res.warm_started ? "TEST continues TRAIN in time: the models run on from TRAIN into TEST (no reset). "
                         : "The models are reset at the first TEST row (rest at its voltage and measured position). ");
  if (res.anchor_s > 0)
    f << "The first " << res.anchor_s << " s of TEST's measurement fix the prediction offset (anchor) and, on a cold start, the "
         "model's start state (models/start_state.h); TEST is scored after them.";
  else
    f << "No anchor: the offset is the model's own.";
  f << "\n\n## TEST error against the measurement\n\n| step | MAE [nm] | RMS [nm] | max [nm] |";
  if (truth) f << " MAE vs truth [nm] |";
  f << "\n|---|---|---|---|" << (truth ? "---|" : "") << "\n";
  f << "| before (base model) | " << res.before_test.mae_nm << " | " << res.before_test.rms_nm << " | " << res.before_test.max_nm << " |";
  if (truth) f << " " << res.before_test_truth.mae_nm << " |";
  f << "\n";
  for (const auto& e : res.effects) {
    f << "| + " << e.family << " | " << e.test_after.mae_nm << " | " << e.test_after.rms_nm << " | " << e.test_after.max_nm << " |";
    if (truth) f << " " << e.test_after_truth.mae_nm << " |";
    f << "\n";
  }
  f << "| **after** | **" << res.after_test.mae_nm << "** | **" << res.after_test.rms_nm << "** | **" << res.after_test.max_nm << "** |";
  if (truth) f << " **" << res.after_test_truth.mae_nm << "** |";
  bool sensor = false;
  for (const auto& e : res.effects) sensor = sensor || e.in_readings;
  if (truth && sensor)
    f << "\n\nMAE vs truth is the stage position's: the sensor effects (in the readings) are left out of it.";
  const Remainder& rem = res.remainder;
  f << "\n\nNoise floor estimated from the TEST data: " << rem.noise_floor << ".\n\n";
}

void md_holds(std::ostream& f, const ReportParts& p) {
  const HoldSummary& hs = p.hs;
  const bool truth = p.truth, holds = p.holds;
  if (holds) {
    f << "## Holds (TEST): MAE inside the holds and end-of-hold error [nm]\n\n"
      << "End-of-hold error: prediction − reference, means over the last 5 s of each of the " << hs.before.end_error_nm.size()
      << " holds.\n\n| | hold MAE vs measured | end-of-hold max / mean abs vs measured |"
      << (truth ? " hold MAE vs truth | end-of-hold max / mean abs vs truth |" : "") << "\n|---|---|---|"
      << (truth ? "---|---|" : "") << "\n";
    auto row = [&](const char* name, const HoldErrors& m, const HoldErrors& t) {
      f << "| " << name << " | " << num(m.in_holds.mae_nm) << " | " << num(m.end_max_abs_nm) << " / " << num(m.end_mean_abs_nm) << " |";
      if (truth) f << " " << num(t.in_holds.mae_nm) << " | " << num(t.end_max_abs_nm) << " / " << num(t.end_mean_abs_nm) << " |";
      f << "\n";
    };
    row("before", hs.before, hs.before_truth);
    row("after", hs.after, hs.after_truth);
    f << "\n";
  }
}

void md_effects(std::ostream& f, const ReportParts& p) {
  const ResidualResult& res = p.res;
  const bool holds = p.holds;
  f << "## Effects found (in the order added; parameters from the final joint fit)\n\n";
  if (res.effects.empty()) f << "None: no family was significant, improved the validation error enough and kept the holds.\n";
  for (std::size_t i = 0; i < res.effects.size(); ++i) {
    const auto& e = res.effects[i];
    f << i + 1 << ". **" << e.family << "**"
      << (e.in_readings ? " (sensor effect: in the readings, not in the stage's position)"
                        : is_gain_family(e.family) ? " (stage effect, gain: scales the motion)" : " (stage effect, additive)")
      << " — " << params_text(e.parameters, e.labels) << "; cross-validated explained variance " << e.explained_variance
      << ", p = " << e.p_value << ", validation MAE −" << 100 * e.validation_gain << " %";
    if (holds) f << " (inside holds −" << 100 * e.hold_validation_gain << " %)";
    f << ".\n";
    if (e.in_readings)
      f << "   It belongs to the model of what the encoder reads, not to the feedforward: the stage position (and the "
           "error against the truth above) leaves it out. The model file marks its terms `acts_on: readings`: the "
           "predictor leaves them out of the predicted position, the drift forecast and the feedforward, and its "
           "estimator expects each reading to be the stage position plus this term.\n";
    else
      f << "   The predictor puts it in the predicted position, the drift forecast and the feedforward.\n";
    for (const auto& c : e.competitors)
      f << "   - competing explanation **" << c.family << "** (" << c.parameters << " parameters, validation −"
        << 100 * c.validation_gain << " %): not taken, " << c.verdict << ".\n";
  }
}

void md_remainder(std::ostream& f, const ResidualResult& res) {
  const Remainder& rem = res.remainder;
  f << "\n## What is left\n\n";
  if (rem.blocks == 0)
    f << "Too little TEST data to test the remainder.\n";
  else if (rem.explained)
    f << "The TEST residual's " << num(rem.block_s) << "-s block means are consistent with white noise of σ "
      << num(rem.noise_sigma_nm) << " nm (p = " << num(rem.p_value) << "): nothing above the noise floor is left.\n";
  else
    f << "**Not explained:** " << num(rem.structure_nm) << " nm RMS of slow structure remains above the noise floor ("
      << num(rem.block_s) << "-s block means against white noise of σ " << num(rem.noise_sigma_nm) << " nm, p = "
      << num(rem.p_value) << "). The model is not complete.\n";
  if (!rem.correlates.empty()) {
    f << "\nTop correlates of what is left (block means):";
    for (std::size_t k = 0; k < rem.correlates.size() && k < 5; ++k)
      f << (k ? "," : "") << " " << rem.correlates[k].first << " " << num(rem.correlates[k].second);
    f << ".\n";
  }
  if (!rem.steps.empty()) {
    // Reported, never added as an effect: a step does not extrapolate (the next slip is anywhere).
    f << "\nStep changes of what is left (mount slips, knocks; not added as an effect):";
    for (std::size_t k = 0; k < rem.steps.size(); ++k)
      f << (k ? "," : "") << " " << num(rem.steps[k].size_nm) << " nm at t = " << num(rem.steps[k].time_s) << " s";
    f << ".\n";
  }
}

void md_rankings(std::ostream& f, const ReportParts& p) {
  const ResidualResult& res = p.res;
  const auto& aug = p.aug;
  const auto& firsts = p.firsts;
  auto table = [&](const std::vector<FamilyScore>& r) {
    f << "| family | explained variance (CV) | p | significant | validation gain (halves) | systematic error removed "
         "| parameters | verdict | note |\n"
         "|---|---|---|---|---|---|---|---|---|\n";
    for (const auto& s : r)
      f << "| " << s.family << " | " << (s.available ? num(s.explained_variance) : "—") << " | "
        << (s.available ? num(s.p_value) : "—") << " | " << (s.significant ? "yes" : "no") << " | "
        << (s.validation_gain != 0 ? num(100 * s.validation_gain) + " % (" + num(100 * s.validation_gain_halves.first) + " / " +
                                         num(100 * s.validation_gain_halves.second) + " %)"
                                   : "")
        << " | " << (s.validation_gain != 0 ? num(100 * s.removed_fraction) + " % (" + num(s.removed_nm) + " nm)" : "")
        << " | " << (s.parameters ? std::to_string(s.parameters) : "")
        << " | " << s.verdict << " | " << s.note << " |\n";
  };
  for (std::size_t i = 0; i < res.effects.size(); ++i) {
    f << "\n### Ranking at step " << i + 1 << "\n\n";
    table(res.effects[i].ranking);
  }
  f << "\n### Final ranking (nothing more added)\n\n";
  table(res.final_ranking);
  f << "\n## Plots\n\n![residual over time](residual_timeseries.png)\n\n![error per step](residual_steps.png)\n";
  for (std::size_t i = 0; i < res.effects.size(); ++i)
    f << "\n![effect " << i + 1 << "](residual_effect" << i + 1 << "_" << res.effects[i].family << ".png)\n";
  f << "\nExplaining variables:";
  for (std::size_t e = 0; e < res.effects.size(); ++e)
    if (firsts[e] < aug.terms().size()) f << " effect " << e + 1 << ": " << explaining_label(aug.terms()[firsts[e]]) << ";";
  f << "\n";
}

}  // namespace

void write_residual_report(const std::string& dir, const ResidualReportContext& ctx, const ResidualResult& res,
                           const io::Dataset& train, const io::Dataset& test, PredictionMode mode) {
  const auto& aug = dynamic_cast<const models::AugmentedModel&>(*res.model);
  ReportParts p{ctx, res, train, test, aug, first_terms(aug, res), {}, res.before_test_truth.n > 0, false};
  const auto& meas = test.axis(ctx.axis).position_nm;
  p.hs.before = hold_errors(res.test_pred_before, meas, test, res.test_mask);
  p.hs.after = hold_errors(res.test_pred_after, meas, test, res.test_mask);
  if (p.truth) {
    p.hs.before_truth = hold_errors(res.test_pred_before, test.axis(ctx.axis).true_position_nm, test, res.test_mask);
    p.hs.after_truth = hold_errors(res.test_position_after.empty() ? res.test_pred_after : res.test_position_after,
                                   test.axis(ctx.axis).true_position_nm, test, res.test_mask);
  }
  p.holds = p.hs.before.valid();
  write_predictions(dir, p);
  write_explain(dir, p, mode);
  models::save_model(dir + "/model.yaml", *res.model);
  write_json(dir, p);
  auto f = open_out(dir + "/report.md");
  md_header(f, p);
  md_holds(f, p);
  md_effects(f, p);
  md_remainder(f, res);
  md_rankings(f, p);
}

}  // namespace piezo::analysis
