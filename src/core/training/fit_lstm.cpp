// Fitting of kind "lstm" (moved from models/lstm_model.cpp; the model itself stays in models/).
#include <cmath>
#include <random>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/models/lstm_model.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/training/hyperparameter_search.h"

namespace piezo::training {

using namespace models;  // the fit code names the model's classes as models/ does

namespace {

// Units = windows of warmup + seq_len consecutive samples of a feature matrix, scored on the last seq_len.
class LstmObjective : public Objective {
 public:
  LstmObjective(const LstmNet& net, const Eigen::MatrixXd& x, const Eigen::VectorXd& y, int seq_len, int warmup);
  std::size_t num_units() const override { return starts_.size(); }
  std::size_t samples_per_unit() const override { return static_cast<std::size_t>(seq_len_); }
  double loss_sum(const Eigen::VectorXd& params, const std::size_t* units, std::size_t n,
                  Eigen::VectorXd* grad) const override;

 private:
  const LstmNet& net_;
  const Eigen::MatrixXd& x_;
  const Eigen::VectorXd& y_;
  int seq_len_, warmup_;
  std::vector<std::size_t> starts_;  // first scored sample of each window
};

LstmObjective::LstmObjective(const LstmNet& net, const Eigen::MatrixXd& x, const Eigen::VectorXd& y, int seq_len,
                             int warmup)
    : net_(net), x_(x), y_(y), seq_len_(seq_len), warmup_(warmup) {
  if (seq_len < 1 || warmup < 0) throw std::runtime_error("lstm: seq_len must be ≥ 1 and warmup ≥ 0");
  const std::size_t n = static_cast<std::size_t>(x.cols());
  for (std::size_t s = static_cast<std::size_t>(warmup); s + static_cast<std::size_t>(seq_len) <= n;
       s += static_cast<std::size_t>(seq_len))
    starts_.push_back(s);
}

double LstmObjective::loss_sum(const Eigen::VectorXd& params, const std::size_t* units, std::size_t n,
                               Eigen::VectorXd* grad) const {
  const Eigen::Index B = static_cast<Eigen::Index>(n), S = warmup_ + seq_len_;
  Eigen::MatrixXd x(x_.rows(), S * B);  // step τ of sequence j in column τ·B + j
  Eigen::MatrixXd ys(seq_len_, B);
  for (Eigen::Index j = 0; j < B; ++j) {
    const Eigen::Index first = static_cast<Eigen::Index>(starts_[units[j]]) - warmup_;
    for (Eigen::Index tau = 0; tau < S; ++tau) x.col(tau * B + j) = x_.col(first + tau);
    ys.col(j) = y_.segment(first + warmup_, seq_len_);
  }
  return net_.sequence_loss_grad(params, x, ys, warmup_, grad);
}

}  // namespace

namespace {

using LstmTrial = NeuralTrial<LstmModel>;

LstmTrial train_lstm(const training::PreparedData& data, const LstmShape& shape, int seq_len, int warmup,
                     training::TrainerConfig cfg) {
  const LstmNet net(shape);
  const LstmObjective train_obj(net, data.x_train, data.y_train, seq_len, warmup);
  const LstmObjective val_obj(net, data.x_validation, data.y_validation, seq_len, warmup);
  if (train_obj.num_units() == 0) throw std::runtime_error("lstm: training data shorter than warmup + seq_len");
  const training::TrainResult r = training::train(train_obj, &val_obj, net.initial_params(cfg.seed), cfg);
  return make_trial(std::make_unique<LstmModel>(data.spec, data.sample_rate_hz, shape, r.params, data.target, warmup),
                    cfg, r, data.target.scale_nm, "batch_size_sequences", {{"seq_len", YAML::Node(seq_len)}});
}

}  // namespace

std::unique_ptr<models::LstmModel> fit_lstm(const FitRequest& request) {
  const training::PreparedData data = training::prepare_data(request, "lstm", {"layers", "hidden", "seq_len", "warmup"});
  LstmShape shape;
  shape.inputs = static_cast<int>(data.spec.size());
  shape.layers = training::option_int(request.options, "layers", 1);
  shape.hidden = training::option_int(request.options, "hidden", 29);
  const int seq_len = training::option_int(request.options, "seq_len", 32);
  const int warmup = training::option_int(request.options, "warmup", 16);
  training::TrainerConfig cfg = training::trainer_config(request, 45, 32);
  if (!request.options || !request.options["grad_clip_norm"]) cfg.grad_clip_norm = 1.0;  // BPTT: avoid blow-ups
  return fit_or_tune(
      "lstm", training::lstm_search_space(), request, cfg,
      [&](training::TrainerConfig c) { return train_lstm(data, shape, seq_len, warmup, c); },
      [&](const training::TrialParams& p, training::TrainerConfig c) {
        LstmShape s = shape;
        s.layers = static_cast<int>(p.number.at("layers"));
        s.hidden = static_cast<int>(p.number.at("hidden"));
        return train_lstm(data, s, seq_len, warmup, with_trial_optimizer(c, p));
      });
}

}  // namespace piezo::training
