// Creep laws combined with Prandtl–Ishlinskii hysteresis (kinds pi_creep_log, pi_creep_lti, pi_creep_fractional).
// All three act on the applied voltage, as the creep seed's transfer functions Y(s)/U(s), and are realised as
// sums of first-order modes y_j' = (V − y_j)/τ_j (so they stream in O(modes) per sample and stay bounded):
//   log:        Σ_j γ·(ln10/m)·LP_{τ_j}(V),  τ_j = t1·10^{j/m}, j < m·decades — step response ≈ γ·ΔV·ln(t/t1)
//               for t1 ≪ t ≪ t1·10^decades (the seed's y = y1(1 + γ log(t/t1)) with y1 folded into γ).
//   lti:        Σ_j g_j·LP_{τ_j}(V) — n spring–damper pairs of G_c(s) = 1/k0 + Σ 1/(c_j s + k_j):
//               g_j = 1/k_j, τ_j = c_j/k_j; 1/k0 is the PI's initial slope.
// With on_hysteresis the same laws act on H instead of V (gains in nm/nm, "nm_per_v" then reads "per nm of H").
//   fractional: b·s^−α by its integral form s^−α = (sin πα/π)∫ τ^α/(τs+1) dlnτ over τ ∈ [τ_min, τ_max]
//               (a multi-mode approximation with finite memory): g_j = b·(sin πα/π)·τ_j^α·Δlnτ;
//               step response ≈ b·ΔV·t^α/Γ(1+α) for τ_min ≪ t ≪ τ_max.
//   prony:      Σ_j g_j·LP_{τ_j}(V or H), τ_j log-spaced on [τ_min, τ_max] (modes_per_decade), g_j ≥ 0 each: a
//               generalised Kelvin–Voigt spectrum. Log, LTI and fractional creep are particular non-negative
//               weight profiles on such a grid; spectra none of them fits are covered too.
// Sizes are bounded (kMaxCreepModes modes, kMaxModesPerDecade per decade, kMaxCreepDecades decades) so a model
// file cannot ask for an unbounded state.
#pragma once

#include <string>
#include <vector>

namespace piezo::models {

enum class CreepKind { kNone, kLog, kLti, kFractional, kProny };
constexpr int kMaxCreepModes = 120, kMaxModesPerDecade = 12, kMaxCreepDecades = 10;
// "pi", "pi_creep_log", ...; with preisach "preisach" or "preisach_creep_prony" (pi_model.h; other creep laws throw).
std::string creep_kind_name(CreepKind k, bool preisach = false);
CreepKind creep_kind_from_name(const std::string& kind, bool* preisach = nullptr);  // throws for other names
// Bounds of the preisach kinds' pieces, so a model file cannot ask for an unbounded state.
constexpr int kMaxPlayOperators = 200, kMaxKnotsPerPlay = 64, kMaxPieces = 4096;

struct CreepParams {
  CreepKind kind = CreepKind::kNone;
  // What the creep modes low-pass: the applied voltage (the seed's Y(s)/U(s)) or the PI output H (creep of the
  // hysteretic displacement: y = b + H + Σ g_j·LP_τj(H), gains then relative, in nm per nm of H).
  bool on_hysteresis = false;
  // log
  double gamma_nm_per_v = 0, t1_s = 1;
  int decades = 5, modes_per_decade = 3;
  // fractional (tau_min_s, tau_max_s, modes_per_decade also place the prony grid)
  double alpha = 0.5, b_nm_per_v = 0, tau_min_s = 1, tau_max_s = 1e5;
  // lti (also the expanded modes of the others; prony: gains_nm_per_v on the grid, taus_s unused)
  std::vector<double> taus_s, gains_nm_per_v;

  // The modes (time constants and gains) this law streams.
  void modes(std::vector<double>& taus_s_out, std::vector<double>& gains_out) const;
  // Unit-gain basis for the linear coefficients: the law is Σ_k θ_k Σ_j basis[k][j]·LP_{τ_j}.
  // log: θ = {γ}; fractional: θ = {b}; lti, prony: θ = gains (basis = identity).
  void basis(std::vector<double>& taus_s_out, std::vector<std::vector<double>>& basis_out) const;
  void set_coefficients(const std::vector<double>& theta);
  std::size_t num_coefficients() const;
  // Throws a clear error when decades, modes_per_decade or the mode count exceed the bounds above.
  void check_sizes() const;
};

// The log-spaced prony grid τ_min·10^(j/m), j = 0..round(m·log10(τ_max/τ_min)).
std::vector<double> log_tau_grid(double tau_min_s, double tau_max_s, int modes_per_decade);

}  // namespace piezo::models
