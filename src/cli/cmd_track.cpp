// `piezo track`: the predictor's estimator run offline over a recording (compensation/track.h) — the fused
// position and its 1σ per row in DIR/track.csv, a table per hold and the forecast table (position forecast per horizon in
// the walk and the holds) in DIR/holds.md, the summary in DIR/track.json.
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <sstream>

#include "args.h"
#include "command.h"
#include "training_rows.h"
#include "plot_script.h"
#include "piezo_compensation/analysis/residual/estimator_fit.h"
#include "piezo_compensation/compensation/track.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/util/format.h"
#include "piezo_compensation/util/json_writer.h"

namespace piezo::cli {
namespace {
namespace fs = std::filesystem;

std::string num(double v, int prec = 2) {
  if (!std::isfinite(v)) return "–";
  std::ostringstream s;
  s << std::fixed << std::setprecision(prec) << v;
  return s.str();
}

void write_csv(const fs::path& path, const compensation::TrackResult& r) {
  std::ofstream f(path);
  if (!f) throw std::runtime_error(path.string() + ": cannot open for writing");
  f << "time_s,applied_v,measured_nm,model_nm,fused_nm,fused_sigma_nm" << (r.has_truth ? ",true_nm" : "") << "\n";
  f << std::setprecision(10);
  for (std::size_t i = 0; i < r.time_s.size(); ++i) {
    f << r.time_s[i] << "," << r.applied_v[i] << "," << r.measured_nm[i] << "," << r.model_nm[i] << ","
      << r.fused_nm[i] << "," << r.fused_sigma_nm[i];
    if (r.has_truth) f << "," << r.true_nm[i];
    f << "\n";
  }
}

std::string hold_table(const compensation::TrackResult& r, const compensation::TrackOptions& o) {
  std::ostringstream s;
  s << "Holds of ≥ " << o.min_hold_s << " s, scored from " << o.settle_skip_s << " s on; end = worst |error| over the last "
    << o.end_window_s << " s. Errors against "
    << (r.has_truth ? "the true position [nm]; ±2σ: the truth within 2σ."
                    : "the mean of the next " + num(o.end_window_s, 0) + " s of readings [nm] (no truth column); ±2σ: the next "
                      "reading within 2·√(σ² + r²), r = " + num(r.reading_sigma_nm, 1) + " nm.")
    << (r.recordings > 1 ? " " + std::to_string(r.recordings) + " recordings, each from a cold start." : "") << "\n\n"
    << "| hold | start [s] | length [s] | V | model MAE | fused MAE | model end | fused end | mean 1σ | within ±2σ |\n"
    << "|---|---|---|---|---|---|---|---|---|---|\n";
  for (std::size_t k = 0; k < r.holds.size(); ++k) {
    const auto& h = r.holds[k];
    s << "| " << k + 1 << " | " << num(h.start_s, 1) << " | " << num(h.end_s - h.start_s, 1) << " | " << num(h.voltage_v, 2)
      << " | " << num(h.model_mae_nm) << " | " << num(h.fused_mae_nm) << " | " << num(h.model_end_nm) << " | "
      << num(h.fused_end_nm) << " | " << num(h.mean_sigma_nm) << " | " << num(100.0 * h.within_2sigma, 1) << " % |\n";
  }
  s << "| all | | | | " << num(r.model_mae_nm) << " | " << num(r.fused_mae_nm) << " | " << num(r.worst_model_end_nm)
    << " | " << num(r.worst_fused_end_nm) << " | | " << num(100.0 * r.within_2sigma, 1) << " % |\n";
  if (r.has_truth)
    s << "\nEvery sample from " << o.score_from_s << " s on: model MAE " << num(r.all_model_mae_nm) << " nm, fused MAE "
      << num(r.all_fused_mae_nm) << " nm, truth within ±2σ " << num(100.0 * r.all_within_2sigma, 1) << " %.\n";
  s << "Model error known (1σ ≤ max(q/8, σ/2)) from " << num(r.zero_known_s, 1) << " s on.\n";
  return s.str();
}

std::string forecast_table(const compensation::TrackResult& r, const compensation::TrackOptions& o) {
  const compensation::ForecastTable& t = r.forecast;
  if (t.horizons_s.empty()) return "";
  const std::string ref = t.against_truth ? "the truth" : "the readings";
  std::ostringstream s;
  s << "Forecast of the position at t + h (fused now, moved by the model under the known voltage and by the error the "
       "estimator expects), against the mean of " << ref << " over the " << num(o.forecast.reference_window_s, 0)
    << " s after t + h; the first column also against the next single " << (t.against_truth ? "truth row" : "reading")
    << ". Walk: the last " << num(o.forecast.walk_s, 0) << " s before each hold; hold: from " << num(o.forecast.hold_from_s, 0)
    << " s after its start. MAE [nm] / share within ±2·√(σ² + σ_ref²) / mean 1σ [nm].\n\n| | next |";
  for (double h : t.horizons_s) s << " " << util::fmt(h, 3) << " s |";
  s << "\n|---|---|";
  for (std::size_t k = 0; k < t.horizons_s.size(); ++k) s << "---|";
  auto cell = [](const compensation::ForecastCell& c) {
    return num(c.mae_nm(), 1) + " / " + num(100.0 * c.coverage(), 1) + " % / " + num(c.mean_sigma_nm(), 1);
  };
  auto row = [&](const char* name, const compensation::ForecastCell& next, const std::vector<compensation::ForecastCell>& cs) {
    s << "\n| " << name << " | " << cell(next) << " |";
    for (const auto& c : cs) s << " " << cell(c) << " |";
  };
  row("walk", t.walk_next, t.walk);
  row("hold", t.hold_next, t.hold);
  s << "\n";
  return s.str();
}

void write_forecast_json(util::JsonWriter& j, const compensation::ForecastTable& t) {
  j.key("forecast_against_truth").value(t.against_truth);
  j.key("forecast").begin_array();
  for (std::size_t k = 0; k < t.horizons_s.size(); ++k) {
    j.begin_object();
    j.key("horizon_s").value(t.horizons_s[k]);
    j.key("walk_mae_nm").value(t.walk[k].mae_nm());
    j.key("walk_within_2sigma").value(t.walk[k].coverage());
    j.key("walk_rows").value(static_cast<double>(t.walk[k].n));
    j.key("hold_mae_nm").value(t.hold[k].mae_nm());
    j.key("hold_within_2sigma").value(t.hold[k].coverage());
    j.key("hold_rows").value(static_cast<double>(t.hold[k].n));
    j.end_object();
  }
  j.end_array();
  j.key("forecast_next_walk_mae_nm").value(t.walk_next.mae_nm());
  j.key("forecast_next_walk_within_2sigma").value(t.walk_next.coverage());
  j.key("forecast_next_hold_mae_nm").value(t.hold_next.mae_nm());
  j.key("forecast_next_hold_within_2sigma").value(t.hold_next.coverage());
}

int run(int argc, char** argv) {
  Args args("track", "Run the predictor's estimator (the model fused with the encoder, docs/predictor.md) over a recording\n"
                     "from a cold start at its first row, as the node would: DIR/track.csv (time_s, applied_v,\n"
                     "measured_nm, model_nm, fused_nm, fused_sigma_nm[, true_nm]), DIR/holds.md, DIR/track.json.");
  args.required("model", "FILE.yaml", "model file (with an estimator: block, written by piezo fit)")
      .files("data", "FILE", "recording (CSV or bag); several: each tracked from its own cold start", true)
      .option("axis", "a|b|c", "axis (default: the model's)")
      .files("identify-on", "FILE", "identify the estimator's noise model (and calibrate its forecast σ) on this\n"
             "recording (the model runs free over it; several: each its own history) instead of the model file's block", false)
      .option("identify-from-s", "T", "with --identify-on: the model runs over the first T of it and only the rest is\n"
              "scored (the part a split fit did not train on)", "0")
      .option("write-model", "FILE.yaml", "with --identify-on: write the model file with the identified estimator: block")
      .option("min-hold-s", "T", "a hold: the voltage unchanged this long [s]", "300")
      .option("settle-skip-s", "T", "score holds from this long after their start [s]", "120")
      .option("end-window-s", "T", "the end of a hold: its last T [s]", "5")
      .option("score-from-s", "T", "also score every sample from T after the first row on [s]", "300")
      .option("start-estimate-s", "T", "the start-up state estimate over the first T [s] (models/start_state.h); 0 = off", "0")
      .option("plot", "", "also write DIR/track.png (python3-matplotlib)")
      .required("out", "DIR", "output directory");
  allow_training_rows_option(args);
  if (!args.parse(argc, argv)) return 0;
  models::ModelPtr model = models::load_model(args.str("model"));
  const std::string axis = args.has("axis") ? args.str("axis") : model->meta.axis;
  std::vector<std::string> notes;
  const io::Dataset data = ros_io::read_recordings(args.list("data"), &notes);
  for (const auto& n : notes) std::cerr << "note: " << n << "\n";
  std::string data_names;
  for (const auto& f : args.list("data")) data_names += (data_names.empty() ? "" : " ") + f;
  models::check_model_matches_data(*model, data, data_names);
  check_training_rows(args, "track", model->meta, data, axis, args.str("model"), "", "tracks");
  if (args.has("identify-on")) {
    const io::Dataset id = ros_io::read_recordings(args.list("identify-on"));
    const double from_s = args.num("identify-from-s");
    std::size_t first = 0;
    while (first < id.size() && id.time_s[first] - id.time_s[0] < from_s) ++first;
    model->meta.estimator = analysis::identify_estimator(*model, id, axis, first).to_yaml();
    if (args.has("write-model")) {
      models::save_model(args.str("write-model"), *model);
      std::cout << "wrote " << args.str("write-model") << " with the estimator identified on " << args.list("identify-on").size() << " recording(s)"
                << " from " << from_s << " s\n";
    }
  } else if (args.has("write-model")) {
    throw UsageError("track: --write-model needs --identify-on");
  } else if (!model->meta.estimator || model->meta.estimator.IsNull()) {
    throw UsageError("track: " + args.str("model") + " has no estimator: block (refit with piezo fit, or give "
                     "--identify-on FILE)");
  }
  compensation::TrackOptions o;
  o.min_hold_s = args.num("min-hold-s");
  o.settle_skip_s = args.num("settle-skip-s");
  o.end_window_s = args.num("end-window-s");
  o.start_estimate_s = args.num("start-estimate-s");
  o.score_from_s = args.num("score-from-s");
  if (!(o.start_estimate_s >= 0)) throw UsageError("track: --start-estimate-s must be a time >= 0 s");
  const compensation::TrackResult r = compensation::track_recording(std::move(model), data, axis, o);

  const fs::path out = args.str("out");
  fs::create_directories(out);
  write_csv(out / "track.csv", r);
  const std::string table = hold_table(r, o) + "\n" + forecast_table(r, o);
  {
    std::ofstream f(out / "holds.md");
    f << "# piezo track: " << args.str("model") << " on " << data_names << " (axis " << axis << ")\n\n"
      << "Estimator: " << r.estimator << "\n\n"
      << (r.start_estimate.empty() ? "" : "Start: " + r.start_estimate + "\n\n") << table;
  }
  {
    std::ofstream f(out / "track.json");
    util::JsonWriter j(f);
    j.begin_object();
    j.key("estimator").value(r.estimator);
    j.key("fusing").value(r.fusing);
    j.key("start_estimate").value(r.start_estimate);
    j.key("holds").value(static_cast<double>(r.holds.size()));
    j.key("hold_model_mae_nm").value(r.model_mae_nm);
    j.key("hold_fused_mae_nm").value(r.fused_mae_nm);
    j.key("worst_model_end_nm").value(r.worst_model_end_nm);
    j.key("worst_fused_end_nm").value(r.worst_fused_end_nm);
    j.key("within_2sigma").value(r.within_2sigma);
    j.key("score_from_s").value(o.score_from_s);
    j.key("all_model_mae_nm").value(r.all_model_mae_nm);
    j.key("all_fused_mae_nm").value(r.all_fused_mae_nm);
    j.key("all_within_2sigma").value(r.all_within_2sigma);
    j.key("zero_known_s").value(r.zero_known_s);
    write_forecast_json(j, r.forecast);
    j.end_object();
  }
  std::cout << "estimator: " << r.estimator << "\n"
            << (r.start_estimate.empty() ? "" : "start: " + r.start_estimate + "\n") << "\n" << table << "\nwrote " << (out / "track.csv").string() << ", holds.md, track.json\n";
  if (args.flag("plot"))
    run_plot_script("track", "track_plot.py", {(out / "track.csv").string(), (out / "track.png").string()});
  return 0;
}

const Register reg("track", "the estimator offline: model fused with the encoder, 1σ, a table per hold", run);

}  // namespace
}  // namespace piezo::cli
