#include "piezo_compensation/features/feature_specs.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace piezo::features {

namespace {
constexpr double kStudyRateHz = 11.0;  // the study's sample rate: its windows in steps become seconds here
FeatureDef def(const std::string& type) {
  FeatureDef f;
  f.type = type;
  return f;
}
}  // namespace

FeatureSpec study_features() {
  FeatureSpec s;
  s.features.push_back(def("voltage"));
  s.features.push_back(def("voltage_step"));
  FeatureDef e60 = def("exp_sum");
  e60.window_s = 60 / kStudyRateHz;
  e60.decay = 0.95;  // the study gives no α; 0.95 keeps weight over most of the 60 steps
  s.features.push_back(e60);
  FeatureDef e300 = def("exp_sum");
  e300.window_s = 300 / kStudyRateHz;
  e300.decay = 0.99;
  s.features.push_back(e300);
  FeatureDef lag = def("lagged_position");
  lag.lag_s = 10 / kStudyRateHz;
  s.features.push_back(lag);
  FeatureDef mean = def("position_mean");
  mean.window_s = 10 / kStudyRateHz;
  s.features.push_back(mean);
  return s;
}

FeatureSpec physics_features() {
  FeatureSpec s;
  s.features.push_back(def("voltage"));
  s.features.push_back(def("voltage_step"));
  s.features.push_back(def("voltage_sq"));
  for (double w_s : {1.0, 5.0, 30.0, 120.0, 600.0}) {
    FeatureDef f = def("step_sum");
    f.window_s = w_s;
    s.features.push_back(f);
  }
  for (double steps : {10.0, 60.0, 300.0})
    for (double a : {0.9, 0.95, 0.99}) {
      FeatureDef f = def("exp_sum");
      f.window_s = steps / kStudyRateHz;
      f.decay = a;
      s.features.push_back(f);
    }
  for (double r : {2.0, 5.0, 10.0, 20.0, 40.0}) {
    FeatureDef f = def("play");
    f.threshold_v = r;
    s.features.push_back(f);
  }
  // Stop thresholds differ from the play ones: stop_r = V − play_r would be exactly collinear.
  for (double r : {1.0, 3.0, 8.0}) {
    FeatureDef f = def("stop");
    f.threshold_v = r;
    s.features.push_back(f);
  }
  // Creep: log-spaced time constants from 1 s to 8.3 h (factor 6), of V and of play outputs (creep acting on
  // the hysteretic displacement is a low-pass of play outputs).
  for (double tau : {1.0, 6.0, 36.0, 216.0, 1296.0, 7776.0, 30000.0}) {
    FeatureDef f = def("lowpass");
    f.time_constant_s = tau;
    s.features.push_back(f);
    for (double r : {5.0, 20.0, 45.0}) {
      FeatureDef p = def("play_lowpass");
      p.threshold_v = r;
      p.time_constant_s = tau;
      s.features.push_back(p);
    }
  }
  return s;
}

FeatureSpec identifiable_on(const FeatureSpec& spec, const DataSpan& span) {
  const double longest_s = span.duration_s / 3.0;
  FeatureSpec out;
  for (const FeatureDef& f : spec.features)
    if (f.time_constant_s <= longest_s && f.window_s <= longest_s && f.lag_s <= longest_s) out.features.push_back(f);
  return out;
}

FeatureSpec candidate_features(const DataSpan* span) {
  if (span) {
    FeatureSpec s = identifiable_on(candidate_features(), *span);
    const double width_v = span->voltage_max_v - span->voltage_min_v;
    // Plays 5/15/30 % of the span wide (the physics set's are in volts, 2–40 V, whatever the stage's range), and
    // their hinges: knots at 20/40/60/80 % of the span, those a play output reaches and bends at (its range, once
    // the voltage has swept the span, is [min + r, max − r]): 10 of the 12.
    if (!(std::isfinite(width_v) && width_v > 0)) return s;
    constexpr double kWidths[] = {0.05, 0.15, 0.30};
    for (double r : kWidths) {
      FeatureDef p = def("play");
      p.threshold_v = r * width_v;
      s.features.push_back(p);
    }
    for (double r : kWidths)
      for (double k : {0.2, 0.4, 0.6, 0.8}) {
        if (!(k > r && k < 1.0 - r)) continue;
        FeatureDef h = def("play_hinge");
        h.threshold_v = r * width_v;
        h.knot_v = span->voltage_min_v + k * width_v;
        s.features.push_back(h);
      }
    return s;
  }
  FeatureSpec s;
  for (double steps : {1.0, 2.0, 5.0, 10.0, 20.0}) {
    FeatureDef f = def("lagged_position");
    f.lag_s = steps / kStudyRateHz;
    s.features.push_back(f);
  }
  FeatureDef mean = def("position_mean");
  mean.window_s = 10 / kStudyRateHz;
  s.features.push_back(mean);
  for (const auto& f : physics_features().features) s.features.push_back(f);
  return s;
}

FeatureSpec voltage_history_features(const DataSpan& span) {
  const double width_v = span.voltage_max_v - span.voltage_min_v;
  if (!(std::isfinite(width_v) && width_v > 0))
    throw std::runtime_error("feature set 'voltage_history': the data's voltage does not vary (span " +
                             std::to_string(width_v) + " V); nothing to place the play operators on");
  if (!(span.duration_s > 0 && span.sample_rate_hz > 0))
    throw std::runtime_error("feature set 'voltage_history': the data has no duration or sample rate");
  FeatureSpec s;
  s.features.push_back(def("voltage"));
  s.features.push_back(def("voltage_step"));  // the LSTM's rate input: 10 % of range on the 5 kHz stages without it, 4 % with
  for (double f : {0.03, 0.10, 0.20, 0.40}) {
    FeatureDef p = def("play");
    p.threshold_v = f * width_v;
    s.features.push_back(p);
  }
  // Creep of the hysteretic displacement, none slower than the data can show nor faster than two samples.
  const double tau_min_s = 2.0 / span.sample_rate_hz;
  double last_tau_s = 0;
  for (double f : {1.0 / 3000, 1.0 / 300, 1.0 / 30, 1.0 / 3}) {
    const double tau_s = std::max(f * span.duration_s, tau_min_s);
    if (tau_s <= last_tau_s) continue;
    last_tau_s = tau_s;
    FeatureDef p = def("play_lowpass");
    p.threshold_v = 0.10 * width_v;
    p.time_constant_s = tau_s;
    s.features.push_back(p);
  }
  return s;
}

FeatureSpec named_features(const std::string& name, const DataSpan* span) {
  if (name == "study") return study_features();
  if (name == "candidates") return candidate_features();
  if (name == "physics") return physics_features();
  if (name == "voltage_history") {
    if (!span) throw std::runtime_error("feature set 'voltage_history' is placed on the training data; none given");
    return voltage_history_features(*span);
  }
  throw std::runtime_error("unknown feature set '" + name + "' (known: study, candidates, physics, voltage_history; a fit also takes lasso and voltage_lasso)");
}

FeatureSpec voltage_only(FeatureSpec spec) {
  spec.features.erase(std::remove_if(spec.features.begin(), spec.features.end(),
                                     [](const FeatureDef& d) { return d.reads_position(); }),
                      spec.features.end());
  return spec;
}

std::vector<std::string> feature_set_names() { return {"study", "candidates", "physics", "voltage_history"}; }

void check_feature_set_name(const std::string& name) {
  const auto names = feature_set_names();
  if (std::find(names.begin(), names.end(), name) == names.end()) named_features(name);
}

}  // namespace piezo::features
