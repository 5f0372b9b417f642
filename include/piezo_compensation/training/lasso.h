// Lasso by coordinate descent on Gram sums, a regularisation path with warm starts, K-fold cross-validation
// over contiguous time blocks (no shuffling: neighbouring samples are strongly correlated), λ_min and λ_1se.
#pragma once

#include <Eigen/Dense>

#include <string>
#include <vector>

#include "piezo_compensation/features/feature_stream.h"
#include "piezo_compensation/training/fit_request.h"
#include "piezo_compensation/training/fit_common.h"

namespace piezo::training {

// min_β (1/2n)‖y − b − Xβ‖² + λ‖β‖₁ given centred G = XᵀX, c = Xᵀy. beta is the warm start and the result.
// Returns the number of sweeps used.
int lasso_cd(const Eigen::MatrixXd& G, const Eigen::VectorXd& c, double n, double lambda, Eigen::VectorXd& beta,
             int max_sweeps = 2000, double tol = 1e-9);

struct LassoOptions {
  int n_lambda = 60;
  double lambda_min_ratio = 1e-4;
  int folds = 5;
};

struct LassoPath {
  std::vector<double> lambdas;             // decreasing
  std::vector<Eigen::VectorXd> coefs;      // fitted on all blocks, per λ (standardised feature units)
  std::vector<double> intercepts;
  std::vector<double> cv_mse, cv_se;       // mean and standard error over folds of the held-out MSE [nm²]
  std::size_t index_min = 0, index_1se = 0;
  double lambda_min() const { return lambdas[index_min]; }
  double lambda_1se() const { return lambdas[index_1se]; }
};

// blocks: Gram sums per contiguous time block (block_gram); folds = blocks.size() (≥ 2 for CV).
LassoPath lasso_path_cv(const std::vector<GramStats>& blocks, const LassoOptions& opt = {},
                        const ProgressFn& progress = {});

// The features with non-zero coefficients at path index `index` (standardisation kept).
features::FeatureSpec select_features(const features::FeatureSpec& spec, const Eigen::VectorXd& coef);

// Markdown: survivors at λ_1se and λ_min with coefficients, CV error, and which of the study's six features
// have a counterpart among the survivors.
std::string lasso_report(const features::FeatureSpec& spec, const LassoPath& path);

// Runs the whole selection on a data set: standardise, block Gram, path with CV. Returns the standardised spec.
struct LassoSelection {
  features::FeatureSpec spec;   // standardised candidates
  LassoPath path;
};
LassoSelection run_lasso(const features::FeatureSpec& candidates, const io::Dataset& data, const std::string& axis,
                         const LassoOptions& opt = {}, const ProgressFn& progress = {});

// The features a lasso fit keeps: run_lasso's survivors at λ_1se, unstandardised (mean and scale cleared, for the
// fit that uses them to standardise on its own data); `report` (optional): lasso_report of the selection.
features::FeatureSpec lasso_survivors(const features::FeatureSpec& candidates, const io::Dataset& data,
                                      const std::string& axis, const ProgressFn& progress = {},
                                      std::string* report = nullptr);

}  // namespace piezo::training
