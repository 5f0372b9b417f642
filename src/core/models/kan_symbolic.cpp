// KAN: closed-form stand-ins for learned edge functions, and the model's formulas.
#include "piezo_compensation/models/kan_model.h"
#include "piezo_compensation/util/format.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <random>
#include <sstream>
#include <stdexcept>

namespace piezo::models {

// ---- symbolic formulas --------------------------------------------------------------------------------------

namespace {

struct LinearFit {
  double a = 0, d = 0, r2 = -std::numeric_limits<double>::infinity();
};

// y ≈ a·u + d by least squares, with R².
LinearFit fit_affine(const std::vector<double>& u, const std::vector<double>& y, double sst) {
  const double n = static_cast<double>(u.size());
  double mu = 0, my = 0;
  for (std::size_t i = 0; i < u.size(); ++i) {
    if (!std::isfinite(u[i])) return {};
    mu += u[i];
    my += y[i];
  }
  mu /= n;
  my /= n;
  double suu = 0, suy = 0;
  for (std::size_t i = 0; i < u.size(); ++i) {
    suu += (u[i] - mu) * (u[i] - mu);
    suy += (u[i] - mu) * (y[i] - my);
  }
  if (suu < 1e-14 * n) return {};
  LinearFit f;
  f.a = suy / suu;
  f.d = my - f.a * mu;
  double sse = 0;
  for (std::size_t i = 0; i < u.size(); ++i) sse += std::pow(y[i] - f.a * u[i] - f.d, 2);
  f.r2 = 1.0 - sse / sst;
  return f;
}

double apply_family(const std::string& fam, double z) {
  if (fam == "sin") return std::sin(z);
  if (fam == "tanh") return std::tanh(z);
  if (fam == "exp") return std::exp(z);
  return z > 0.0 ? std::log(z) : std::numeric_limits<double>::quiet_NaN();  // log
}

int complexity(const std::string& fam) {
  static const std::vector<std::string> order{"x", "x^2", "x^3", "tanh", "sin", "exp", "log"};
  return static_cast<int>(std::find(order.begin(), order.end(), fam) - order.begin());
}

std::string num(double v) { return util::fmt(v, 4); }

}  // namespace

std::string SymbolicFit::formula(const std::string& var) const {
  if (family == "x" || family == "x^2" || family == "x^3") {
    std::string s = num(coef[0]);
    const char* pw[] = {"", "", "^2", "^3"};
    for (std::size_t p = 1; p < coef.size(); ++p) {
      s += coef[p] < 0 ? " - " : " + ";
      s += num(std::abs(coef[p])) + "·" + var + pw[p];
    }
    return s;
  }
  std::string inner = num(coef[1]) + "·" + var + (coef[2] < 0 ? " - " : " + ") + num(std::abs(coef[2]));
  return num(coef[0]) + "·" + family + "(" + inner + ")" + (coef[3] < 0 ? " - " : " + ") + num(std::abs(coef[3]));
}

SymbolicFit fit_symbolic(const std::vector<double>& x, const std::vector<double>& y) {
  if (x.size() != y.size() || x.size() < 5) throw std::runtime_error("fit_symbolic: need at least 5 samples");
  const std::size_t n = x.size();
  double my = 0;
  for (double v : y) my += v;
  my /= static_cast<double>(n);
  double sst = 0;
  for (double v : y) sst += (v - my) * (v - my);
  if (sst < 1e-18 * static_cast<double>(n)) return {"x", {my, 0.0}, 1.0};

  std::vector<SymbolicFit> fits;
  for (int deg = 1; deg <= 3; ++deg) {
    Eigen::MatrixXd V(static_cast<Eigen::Index>(n), deg + 1);
    Eigen::VectorXd Y = Eigen::Map<const Eigen::VectorXd>(y.data(), static_cast<Eigen::Index>(n));
    for (std::size_t i = 0; i < n; ++i)
      for (int p = 0; p <= deg; ++p) V(static_cast<Eigen::Index>(i), p) = std::pow(x[i], p);
    const Eigen::VectorXd c = V.colPivHouseholderQr().solve(Y);
    const double sse = (V * c - Y).squaredNorm();
    fits.push_back({deg == 1 ? "x" : deg == 2 ? "x^2" : "x^3", std::vector<double>(c.data(), c.data() + c.size()),
                    1.0 - sse / sst});
  }
  double xlo = *std::min_element(x.begin(), x.end()), xhi = *std::max_element(x.begin(), x.end());
  const double xspan = std::max(xhi - xlo, 1e-12);
  std::vector<double> u(n);
  for (const std::string fam : {"tanh", "sin", "exp", "log"}) {
    // Coarse grid over the inner scale b (per unit of the input span) and shift c, then local refinement.
    double best_b = 0, best_c = 0;
    LinearFit best;
    auto score = [&](double b, double c) {
      for (std::size_t i = 0; i < n; ++i) {
        const double z = b * x[i] + c;
        u[i] = (fam == "exp" && std::abs(z) > 30.0) ? std::numeric_limits<double>::quiet_NaN() : apply_family(fam, z);
      }
      const LinearFit f = fit_affine(u, y, sst);
      if (f.r2 > best.r2) {
        best = f;
        best_b = b;
        best_c = c;
      }
    };
    const double b_max = 8.0 * 2.0 / xspan;
    const double c_max = fam == "sin" ? 3.14159 : 4.0;
    for (int ib = -32; ib <= 32; ++ib) {
      if (ib == 0) continue;
      for (int ic = -12; ic <= 12; ++ic) score(b_max * ib / 32.0, c_max * ic / 12.0);
    }
    double db = b_max / 32.0, dc = c_max / 12.0;
    for (int round = 0; round < 12; ++round) {
      db *= 0.5;
      dc *= 0.5;
      const double b0 = best_b, c0 = best_c;
      for (int ib = -2; ib <= 2; ++ib)
        for (int ic = -2; ic <= 2; ++ic) score(b0 + db * ib, c0 + dc * ic);
    }
    if (std::isfinite(best.r2)) fits.push_back({fam, {best.a, best_b, best_c, best.d}, best.r2});
  }
  double best_r2 = -std::numeric_limits<double>::infinity();
  for (const auto& f : fits) best_r2 = std::max(best_r2, f.r2);
  const SymbolicFit* pick = nullptr;
  for (const auto& f : fits)
    if (f.r2 >= best_r2 - 1e-4 && (!pick || complexity(f.family) < complexity(pick->family))) pick = &f;
  return *pick;
}


std::string KanModel::formulas() const {
  std::ostringstream os;
  const auto& spec = stream_.spec();
  os << "KAN " << net_.shape().widths.size() - 1 << " layer(s), grid " << net_.shape().grid << ", order "
     << net_.shape().order << "; position_nm = " << num(target_.mean_nm) << " + " << num(target_.scale_nm)
     << " · output\n";
  for (std::size_t i = 0; i < spec.size(); ++i) {
    const double mean = spec.mean.empty() ? 0.0 : spec.mean[i];
    os << "  z" << i << " = (" << spec.features[i].name() << (mean < 0 ? " + " : " - ") << num(std::abs(mean))
       << ") / " << num(spec.scale.empty() ? 1.0 : spec.scale[i]) << "\n";
  }
  for (int l = 0; l < net_.num_layers(); ++l) {
    const int n_in = net_.shape().widths[static_cast<std::size_t>(l)], n_out = net_.shape().widths[static_cast<std::size_t>(l + 1)];
    const bool last = l + 1 == net_.num_layers();
    for (int i = 0; i < n_in; ++i) {
      const double* t = net_.knots(l, i);
      const double lo = t[net_.shape().order], hi = t[net_.num_knots() - 1 - net_.shape().order];
      const std::string var = l == 0 ? "z" + std::to_string(i) : "h" + std::to_string(l) + "_" + std::to_string(i);
      for (int j = 0; j < n_out; ++j) {
        std::vector<double> xs, ys;
        for (int s = 0; s <= 100; ++s) {
          xs.push_back(lo + (hi - lo) * s / 100.0);
          ys.push_back(net_.edge(params_.data(), l, i, j, xs.back()));
        }
        const SymbolicFit f = fit_symbolic(xs, ys);
        os << "  layer " << l << ", " << var << " -> " << (last ? "output" : "h" + std::to_string(l + 1) + "_" + std::to_string(j))
           << ": " << f.formula(var) << "   (R² " << std::fixed << std::setprecision(5) << f.r2 << ")\n";
        os.unsetf(std::ios::fixed);
      }
    }
  }
  return os.str();
}

}  // namespace piezo::models
