// Scoring a family on the current residual: blocked cross-validation of every variant, significance against
// circular-shift draws (the same search with the alignment destroyed) or the red-noise periodogram.
#include <algorithm>
#include <cmath>
#include <sstream>

#include "piezo_compensation/analysis/residual/residual_context.h"

namespace piezo::analysis::detail {

using models::EffectTerm;

namespace {

double normal_tail(double z) { return 0.5 * std::erfc(z / std::sqrt(2.0)); }

// The observed best against the best of each shifted draw: a Gaussian tail beyond the draws, the empirical rank
// within them.
double shift_p_value(double best, const std::vector<double>& null_max, std::string& note) {
  double m = 0, v = 0, above = 0;
  for (double x : null_max) m += x;
  m /= static_cast<double>(null_max.size());
  for (double x : null_max) {
    v += (x - m) * (x - m);
    if (x >= best) above += 1;
  }
  const double sd = std::sqrt(v / static_cast<double>(std::max<std::size_t>(1, null_max.size() - 1)));
  const double p_emp = (1.0 + above) / (1.0 + static_cast<double>(null_max.size()));
  const double p_gauss = sd > 0 ? normal_tail((best - m) / sd) : (best > m ? 0.0 : 1.0);
  std::ostringstream os;
  os << "circular-shift null: mean " << m << ", sd " << sd << " over " << null_max.size() << " draws";
  note = os.str();
  return above > 0 ? p_emp : std::min(p_emp, p_gauss);
}

std::vector<double> decimate(const std::vector<double>& Z, std::size_t n, std::size_t k, std::size_t stride) {
  std::vector<double> Zd;
  Zd.reserve((n / stride + 1) * k);
  for (std::size_t i = 0; i < n; i += stride)
    Zd.insert(Zd.end(), Z.begin() + static_cast<long>(i * k), Z.begin() + static_cast<long>((i + 1) * k));
  return Zd;
}

}  // namespace

FamilyScore score_family(Family family, const Context& c, const std::vector<EffectTerm>& fixed, const Level& level,
                         const std::vector<double>& residual, const std::vector<double>& position,
                         const ResidualOptions& o, std::mt19937_64& rng) {
  FamilyScore fs;
  fs.family = traits(family).name;
  const std::size_t n = residual.size();
  const std::size_t stride = std::max<std::size_t>(1, (n + o.max_score_samples - 1) / o.max_score_samples);
  FamilyCandidates fc = candidates(family, c, residual, position, stride);
  if (c.max_time_constant_s > 0.0) {  // no time constant the validation part cannot judge
    const std::size_t all = fc.variants.size();
    fc.variants.erase(std::remove_if(fc.variants.begin(), fc.variants.end(),
                                     [&](const Candidate& v) {
                                       return std::any_of(v.terms.begin(), v.terms.end(), [&](const EffectTerm& t) {
                                         return t.time_constant_s > c.max_time_constant_s * (1 + 1e-9);
                                       });
                                     }),
                      fc.variants.end());
    if (all > 0 && fc.variants.empty() && fc.note.empty())
      fc.note = "every time constant longer than half the validation part";
  }
  fs.variants = fc.variants.size();
  fs.note = fc.note;
  if (fc.variants.empty()) {
    fs.available = false;
    return fs;
  }
  std::vector<double> rd;
  for (std::size_t i = 0; i < n; i += stride) rd.push_back(residual[i]);
  const std::size_t nd = rd.size();
  std::vector<std::size_t> shifts;
  if (!fc.spectral) {
    std::uniform_int_distribution<std::size_t> pick(nd / 10, nd - nd / 10);
    for (int s = 0; s < o.permutations; ++s) shifts.push_back(pick(rng));
  }
  std::vector<double> null_max(shifts.size(), -1e300);
  double best = -1e300;
  for (const auto& cand : fc.variants) {
    std::size_t k = 0;
    const std::vector<double> Z = regressors(c, fixed, level.offset_nm, cand.terms, k);
    const CvScore s = cv_explained_variance(rd, decimate(Z, n, k, stride), k, o.cv_folds, shifts);
    if (s.explained_variance > best) {
      best = s.explained_variance;
      fs.best = cand;
    }
    for (std::size_t q = 0; q < shifts.size(); ++q) null_max[q] = std::max(null_max[q], s.null_explained_variance[q]);
  }
  fs.explained_variance = best;
  if (fc.spectral) fs.p_value = fc.peak.p_value;
  else if (!null_max.empty()) fs.p_value = shift_p_value(best, null_max, fs.note);
  else fs.p_value = 0.0;  // no draws asked for: the family is already accepted, only its variant is chosen
  fs.significant = fs.p_value < o.acceptance.alpha && fs.explained_variance >= o.acceptance.min_explained_variance;
  return fs;
}

void describe(const std::vector<EffectTerm>& terms, std::size_t first, std::size_t count, FoundEffect& e) {
  for (std::size_t i = first; i < first + count; ++i) {
    const EffectTerm& t = terms[i];
    auto w = [&](std::size_t q) { return t.weight[q] / t.scale[q]; };  // per raw unit
    const std::string pre = count > 1 ? "term" + std::to_string(i - first) + "_" : "";
    const models::TermKind kind = t.kind();
    if (kind == models::TermKind::kSinCos) {
      e.parameters[pre + "amplitude_nm"] = std::hypot(w(0), w(1));
      e.parameters[pre + "phase_rad"] = std::atan2(w(1), w(0));
    } else if (kind == models::TermKind::kLinear || kind == models::TermKind::kPlay) {
      if (t.signal == models::kSignalTime) {
        e.parameters["drift_nm_per_h"] = w(0) * 3600.0;
      } else {
        const std::string unit =
            t.signal == models::kSignalVoltage || io::is_voltage_column(t.signal) ? "nm_per_v" : "nm_per_unit";
        e.parameters[pre + (kind == models::TermKind::kPlay ? "play_gain_" : "gain_") + unit] = w(0);
      }
    } else if (kind == models::TermKind::kRate) {
      e.parameters["gain_nm_per_v_step"] = w(0);
      e.parameters["gain_nm_per_abs_v_step"] = w(1);
      e.parameters["gain_nm_per_signed_v2_step"] = w(2);
    } else if (t.is_gain()) {
      // f(s) = w·g(s)/(q − ref) per unit of the centred signal: relative gain change per signal unit; on the
      // voltage the change is in nm per volt (the relative change is that over the stage's nm/V).
      const std::string sig = t.signal == models::kSignalTime ? "per_h" : "per_unit";
      const double k = t.signal == models::kSignalTime ? 3600.0 : 1.0;
      e.parameters[pre + (t.scales == models::kSignalVoltage ? "gain_change_nm_per_v_" : "gain_change_") + sig] =
          w(0) / t.pre_scale * k;
      if (kind == models::TermKind::kGainQuadratic) e.parameters[pre + "gain_change_quadratic"] = t.weight[1] / t.scale[1];
      e.labels["scales"] = t.scales;
      e.labels["form"] = kind == models::TermKind::kGain ? "linear" : "quadratic";
    } else if (kind == models::TermKind::kPowers) {
      e.parameters["quadratic_nm"] = w(0);
      e.parameters["cubic_nm"] = w(1);
    }
  }
}

}  // namespace piezo::analysis::detail
