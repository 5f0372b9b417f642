#include "piezo_compensation/models/creep_models.h"

#include <cmath>
#include <stdexcept>

namespace piezo::models {

std::string creep_kind_name(CreepKind k, bool preisach) {
  if (preisach) {
    if (k == CreepKind::kNone) return "preisach";
    if (k == CreepKind::kProny) return "preisach_creep_prony";
    throw std::runtime_error("the preisach kinds have prony creep or none, not " + creep_kind_name(k));
  }
  switch (k) {
    case CreepKind::kNone: return "pi";
    case CreepKind::kLog: return "pi_creep_log";
    case CreepKind::kLti: return "pi_creep_lti";
    case CreepKind::kFractional: return "pi_creep_fractional";
    case CreepKind::kProny: return "pi_creep_prony";
  }
  return "pi";
}

CreepKind creep_kind_from_name(const std::string& kind, bool* preisach) {
  if (preisach) *preisach = kind == "preisach" || kind == "preisach_creep_prony";
  if (kind == "preisach" && preisach) return CreepKind::kNone;
  if (kind == "preisach_creep_prony" && preisach) return CreepKind::kProny;
  if (kind == "pi") return CreepKind::kNone;
  if (kind == "pi_creep_log") return CreepKind::kLog;
  if (kind == "pi_creep_lti") return CreepKind::kLti;
  if (kind == "pi_creep_fractional") return CreepKind::kFractional;
  if (kind == "pi_creep_prony") return CreepKind::kProny;
  throw std::runtime_error("not a PI kind: '" + kind + "'");
}

std::vector<double> log_tau_grid(double tau_min_s, double tau_max_s, int modes_per_decade) {
  if (!(tau_min_s > 0 && tau_max_s >= tau_min_s && std::isfinite(tau_max_s)))
    throw std::runtime_error("creep: need 0 < tau_min_s <= tau_max_s, got " + std::to_string(tau_min_s) + ", " +
                             std::to_string(tau_max_s));
  if (modes_per_decade < 1 || modes_per_decade > kMaxModesPerDecade)
    throw std::runtime_error("creep: modes_per_decade must be in 1.." + std::to_string(kMaxModesPerDecade) + ", got " +
                             std::to_string(modes_per_decade));
  const double decades = std::log10(tau_max_s / tau_min_s);
  if (decades > kMaxCreepDecades)
    throw std::runtime_error("creep: tau_max_s / tau_min_s spans " + std::to_string(decades) + " decades (at most " +
                             std::to_string(kMaxCreepDecades) + ")");
  const int J = static_cast<int>(std::round(decades * modes_per_decade)) + 1;
  std::vector<double> taus;
  for (int j = 0; j < J; ++j) taus.push_back(tau_min_s * std::pow(10.0, double(j) / modes_per_decade));
  return taus;
}

void CreepParams::check_sizes() const {
  auto bad = [](const std::string& what) { throw std::runtime_error("creep: " + what); };
  if (kind == CreepKind::kLog) {
    if (decades < 1 || decades > kMaxCreepDecades)
      bad("decades must be in 1.." + std::to_string(kMaxCreepDecades) + ", got " + std::to_string(decades));
    if (modes_per_decade < 1 || modes_per_decade > kMaxModesPerDecade)
      bad("modes_per_decade must be in 1.." + std::to_string(kMaxModesPerDecade) + ", got " +
          std::to_string(modes_per_decade));
  }
  if (kind == CreepKind::kFractional || kind == CreepKind::kProny) log_tau_grid(tau_min_s, tau_max_s, modes_per_decade);
  if (kind == CreepKind::kLti && taus_s.size() > static_cast<std::size_t>(kMaxCreepModes))
    bad("at most " + std::to_string(kMaxCreepModes) + " lti modes, got " + std::to_string(taus_s.size()));
}

void CreepParams::basis(std::vector<double>& taus, std::vector<std::vector<double>>& B) const {
  taus.clear();
  B.clear();
  switch (kind) {
    case CreepKind::kNone: return;
    case CreepKind::kLog: {
      check_sizes();
      if (!(t1_s > 0)) throw std::runtime_error("log creep: t1_s must be > 0");
      const int J = decades * modes_per_decade;
      for (int j = 0; j < J; ++j) taus.push_back(t1_s * std::pow(10.0, double(j) / modes_per_decade));
      B.assign(1, std::vector<double>(J, std::log(10.0) / modes_per_decade));
      return;
    }
    case CreepKind::kFractional: {
      if (!(alpha > 0 && alpha < 1)) throw std::runtime_error("fractional creep: alpha must be in (0, 1)");
      if (!(tau_max_s > tau_min_s)) throw std::runtime_error("fractional creep: need 0 < tau_min_s < tau_max_s");
      taus = log_tau_grid(tau_min_s, tau_max_s, modes_per_decade);
      const double dln = std::log(10.0) / modes_per_decade;
      std::vector<double> row;
      for (double tau : taus) row.push_back(std::sin(M_PI * alpha) / M_PI * std::pow(tau, alpha) * dln);
      B.push_back(row);
      return;
    }
    case CreepKind::kProny: {
      taus = log_tau_grid(tau_min_s, tau_max_s, modes_per_decade);
      for (std::size_t j = 0; j < taus.size(); ++j) {
        std::vector<double> row(taus.size(), 0.0);
        row[j] = 1.0;
        B.push_back(row);
      }
      return;
    }
    case CreepKind::kLti: {
      check_sizes();
      taus = taus_s;
      for (std::size_t j = 0; j < taus.size(); ++j) {
        if (!(taus[j] > 0)) throw std::runtime_error("lti creep: time constants must be > 0");
        std::vector<double> row(taus.size(), 0.0);
        row[j] = 1.0;
        B.push_back(row);
      }
      return;
    }
  }
}

std::size_t CreepParams::num_coefficients() const {
  switch (kind) {
    case CreepKind::kNone: return 0;
    case CreepKind::kLog:
    case CreepKind::kFractional: return 1;
    case CreepKind::kLti: return taus_s.size();
    case CreepKind::kProny: return log_tau_grid(tau_min_s, tau_max_s, modes_per_decade).size();
  }
  return 0;
}

void CreepParams::set_coefficients(const std::vector<double>& theta) {
  if (theta.size() != num_coefficients()) throw std::runtime_error("creep: wrong number of coefficients");
  if (kind == CreepKind::kLog) gamma_nm_per_v = theta[0];
  if (kind == CreepKind::kFractional) b_nm_per_v = theta[0];
  if (kind == CreepKind::kLti || kind == CreepKind::kProny) gains_nm_per_v = theta;
}

void CreepParams::modes(std::vector<double>& taus, std::vector<double>& gains) const {
  std::vector<std::vector<double>> B;
  basis(taus, B);
  gains.assign(taus.size(), 0.0);
  std::vector<double> theta;
  if (kind == CreepKind::kLog) theta = {gamma_nm_per_v};
  if (kind == CreepKind::kFractional) theta = {b_nm_per_v};
  if (kind == CreepKind::kLti || kind == CreepKind::kProny) theta = gains_nm_per_v;
  if (theta.size() != B.size()) throw std::runtime_error("creep: gains and time constants differ in number");
  for (std::size_t k = 0; k < B.size(); ++k)
    for (std::size_t j = 0; j < taus.size(); ++j) gains[j] += theta[k] * B[k][j];
}

}  // namespace piezo::models
