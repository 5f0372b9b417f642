#include "piezo_compensation/training/lasso.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/features/feature_specs.h"

namespace piezo::training {

int lasso_cd(const Eigen::MatrixXd& G, const Eigen::VectorXd& c, double n, double lambda, Eigen::VectorXd& beta,
             int max_sweeps, double tol) {
  const Eigen::Index p = G.rows();
  if (beta.size() != p) beta = Eigen::VectorXd::Zero(p);
  Eigen::VectorXd r = c - G * beta;  // gradient of ½‖y − Xβ‖² (negated), kept up to date
  const double thr = n * lambda;
  const double scale = std::max(1e-300, G.diagonal().maxCoeff());
  int sweep = 0;
  for (; sweep < max_sweeps; ++sweep) {
    double max_change = 0;
    for (Eigen::Index j = 0; j < p; ++j) {
      const double gjj = G(j, j);
      if (gjj <= 0) continue;
      const double z = r(j) + gjj * beta(j);
      const double nb = z > thr ? (z - thr) / gjj : (z < -thr ? (z + thr) / gjj : 0.0);
      const double d = nb - beta(j);
      if (d != 0) {
        r.noalias() -= G.col(j) * d;
        beta(j) = nb;
        max_change = std::max(max_change, std::abs(d) * std::sqrt(gjj / scale));
      }
    }
    if (max_change < tol * (1 + beta.cwiseAbs().maxCoeff())) break;
  }
  return sweep + 1;
}

LassoPath lasso_path_cv(const std::vector<GramStats>& blocks, const LassoOptions& opt, const ProgressFn& progress) {
  if (blocks.empty()) throw std::runtime_error("lasso: no data blocks");
  GramStats all = blocks[0];
  for (std::size_t k = 1; k < blocks.size(); ++k) all += blocks[k];
  const Eigen::Index p = all.sx.size();
  const Eigen::MatrixXd G = all.centered_xx();
  const Eigen::VectorXd c = all.centered_xy();
  LassoPath path;
  const double lmax = std::max(1e-12, c.cwiseAbs().maxCoeff() / all.n);
  const int L = std::max(2, opt.n_lambda);
  for (int i = 0; i < L; ++i) path.lambdas.push_back(lmax * std::pow(opt.lambda_min_ratio, double(i) / (L - 1)));

  const std::size_t K = blocks.size();
  const double total_steps = double(L) * double(K + 1);
  double steps = 0;
  Eigen::VectorXd beta = Eigen::VectorXd::Zero(p);
  for (int i = 0; i < L; ++i) {
    lasso_cd(G, c, all.n, path.lambdas[i], beta);
    path.coefs.push_back(beta);
    path.intercepts.push_back(all.mean_y() - all.mean_x().dot(beta));
    if (progress) progress(++steps, total_steps, "lasso path");
  }
  path.cv_mse.assign(L, 0.0);
  path.cv_se.assign(L, 0.0);
  if (K >= 2) {
    std::vector<std::vector<double>> fold_mse(L, std::vector<double>(K));
    for (std::size_t k = 0; k < K; ++k) {
      GramStats tr = all;
      tr -= blocks[k];
      const Eigen::MatrixXd Gk = tr.centered_xx();
      const Eigen::VectorXd ck = tr.centered_xy();
      Eigen::VectorXd b = Eigen::VectorXd::Zero(p);
      for (int i = 0; i < L; ++i) {
        lasso_cd(Gk, ck, tr.n, path.lambdas[i], b);
        const double icpt = tr.mean_y() - tr.mean_x().dot(b);
        fold_mse[i][k] = std::max(0.0, blocks[k].sse(b, icpt)) / blocks[k].n;
        if (progress) progress(++steps, total_steps, "lasso path");
      }
    }
    for (int i = 0; i < L; ++i) {
      double m = 0, v = 0;
      for (double e : fold_mse[i]) m += e;
      m /= double(K);
      for (double e : fold_mse[i]) v += (e - m) * (e - m);
      path.cv_mse[i] = m;
      path.cv_se[i] = std::sqrt(v / double(K - 1) / double(K));
    }
    path.index_min = static_cast<std::size_t>(std::min_element(path.cv_mse.begin(), path.cv_mse.end()) - path.cv_mse.begin());
    const double bound = path.cv_mse[path.index_min] + path.cv_se[path.index_min];
    path.index_1se = path.index_min;
    for (int i = 0; i <= static_cast<int>(path.index_min); ++i)
      if (path.cv_mse[i] <= bound) {
        path.index_1se = i;  // the largest λ (sparsest model) within one SE of the minimum
        break;
      }
  } else {
    path.index_min = path.index_1se = L - 1;
  }
  return path;
}

features::FeatureSpec select_features(const features::FeatureSpec& spec, const Eigen::VectorXd& coef) {
  features::FeatureSpec out;
  for (std::size_t j = 0; j < spec.size(); ++j) {
    if (coef(j) == 0) continue;
    out.features.push_back(spec.features[j]);
    if (!spec.mean.empty()) {
      out.mean.push_back(spec.mean[j]);
      out.scale.push_back(spec.scale[j]);
    }
  }
  return out;
}

namespace {
// Which study feature a candidate stands for (same type and window), for the comparison table.
std::string study_match(const features::FeatureDef& f) {
  const features::FeatureSpec s = features::study_features();
  const char* names[] = {"V_t", "dV_t", "exp sum 60 steps", "exp sum 300 steps", "D_{t-10}", "mean of 10 past D"};
  for (std::size_t i = 0; i < s.size(); ++i) {
    const auto& g = s.features[i];
    if (g.type == f.type && std::abs(g.window_s - f.window_s) < 1e-9 && std::abs(g.lag_s - f.lag_s) < 1e-9 &&
        (g.type != "exp_sum" || std::abs(g.decay - f.decay) < 1e-9))
      return names[i];
  }
  return "";
}
}  // namespace

std::string lasso_report(const features::FeatureSpec& spec, const LassoPath& path) {
  std::ostringstream os;
  char buf[256];
  os << "## Lasso feature selection\n\n"
     << "Coordinate descent on standardised features, " << path.lambdas.size() << " λ values, "
     << "cross-validation over contiguous time blocks.\n\n";
  std::snprintf(buf, sizeof buf, "- λ_min = %.4g (CV RMS %.3f nm, %ld features)\n- λ_1se = %.4g (CV RMS %.3f nm, %ld features)\n\n",
                path.lambda_min(), std::sqrt(path.cv_mse[path.index_min]),
                long((path.coefs[path.index_min].array() != 0).count()), path.lambda_1se(),
                std::sqrt(path.cv_mse[path.index_1se]), long((path.coefs[path.index_1se].array() != 0).count()));
  os << buf;
  os << "| feature | coef at λ_1se [nm/σ] | coef at λ_min [nm/σ] | study counterpart |\n|---|---|---|---|\n";
  const Eigen::VectorXd& a = path.coefs[path.index_1se];
  const Eigen::VectorXd& b = path.coefs[path.index_min];
  std::vector<std::size_t> order;
  for (std::size_t j = 0; j < spec.size(); ++j)
    if (a(j) != 0 || b(j) != 0) order.push_back(j);
  std::sort(order.begin(), order.end(), [&](std::size_t x, std::size_t y) { return std::abs(b(x)) > std::abs(b(y)); });
  for (std::size_t j : order) {
    std::snprintf(buf, sizeof buf, "| %s | %.4g | %.4g | %s |\n", spec.features[j].name().c_str(), a(j), b(j),
                  study_match(spec.features[j]).c_str());
    os << buf;
  }
  os << "\nThe study's choice: V, ΔV, exp sums over 60 and 300 steps, D_{t−10}, mean of 10 D. Of these, survive at λ_1se: ";
  int hits = 0;
  for (std::size_t j = 0; j < spec.size(); ++j)
    if (a(j) != 0 && !study_match(spec.features[j]).empty()) os << (hits++ ? ", " : "") << study_match(spec.features[j]);
  os << (hits ? "" : "none") << ".\n";
  return os.str();
}

LassoSelection run_lasso(const features::FeatureSpec& candidates, const io::Dataset& data, const std::string& axis,
                         const LassoOptions& opt, const ProgressFn& progress) {
  LassoSelection sel;
  sel.spec = fit_standardisation(candidates, data, axis);
  const auto blocks = block_gram(sel.spec, data, axis, std::max(1, opt.folds), progress);
  sel.path = lasso_path_cv(blocks, opt, progress);
  return sel;
}

features::FeatureSpec lasso_survivors(const features::FeatureSpec& candidates, const io::Dataset& data,
                                      const std::string& axis, const ProgressFn& progress, std::string* report) {
  const LassoSelection sel = run_lasso(candidates, data, axis, {}, progress);
  features::FeatureSpec chosen = select_features(sel.spec, sel.path.coefs[sel.path.index_1se]);
  if (report) *report = lasso_report(sel.spec, sel.path);
  chosen.mean.clear();
  chosen.scale.clear();
  return chosen;
}

}  // namespace piezo::training
