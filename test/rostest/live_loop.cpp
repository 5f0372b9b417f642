// The whole live loop on the simulated device: compensated with a clean model → the
// thermal drift switched on mid-run → the residual watch WARNs → ~snapshot → `piezo residual` on the bag names the
// temperature → ~reload_model with the augmented model → the rolling MAE comes back under the threshold.
#include <diagnostic_msgs/DiagnosticArray.h>
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <std_msgs/Float64.h>
#include <std_srvs/SetBool.h>
#include <std_srvs/Trigger.h>
#include <yaml-cpp/yaml.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iomanip>
#include <iostream>
#include <thread>

#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/IntendedMotion.h"
#include "piezo_compensation/Prediction.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/util/child_process.h"

namespace fs = std::filesystem;
using piezo_compensation::EncoderPosition;
using piezo_compensation::IntendedMotion;

namespace {

struct Loop {
  ros::NodeHandle nh;
  std::unique_ptr<piezo::protocols::Protocol> walk;
  std::size_t k = 0;
  ros::Publisher intended;
  ros::Subscriber enc, mae, diag, pred;
  std::ofstream trace;  // every prediction of axis c, for reading a failed run
  double mae_nm = std::nan(""), mae_stamp = 0.0;
  std::string diag_message;
  std::string snapshot_diag;  // the predictor's "snapshot buffer" status: rings grown, capacity
  int diag_level = -1;
  bool watch_warned = false;
  std::size_t readings = 0;
  std::function<void(double)> on_mae;  // called with every rolling-MAE figure [nm]

  Loop() {
    // a random walk through the compensated axis, one intent per encoder sample (seeded: the same every run)
    walk = piezo::protocols::make_protocol("random_walk", YAML::Load("{duration_s: 20000}"), 11.0, 5);
    intended = nh.advertise<IntendedMotion>("/mm1/c/intended", 1);
    enc = nh.subscribe<EncoderPosition>("/mm1/c/encoder", 50, [this](const EncoderPosition::ConstPtr&) {
      ++readings;
      IntendedMotion m;
      m.header.stamp = ros::Time::now();
      m.mode = IntendedMotion::VOLTAGE;
      m.voltage = walk->at(std::min(k++, walk->size() - 1)).voltage_v[2];
      intended.publish(m);
    });
    pred = nh.subscribe<piezo_compensation::Prediction>(
        "/mm1/c/prediction", 100, [this](const piezo_compensation::Prediction::ConstPtr& p) {
          if (trace.is_open())
            trace << std::setprecision(12) << p->header.stamp.toSec() << "," << p->measured_position * 1e9 << ","
                  << p->predicted_position * 1e9 << "," << p->intended_position * 1e9 << "," << p->commanded_voltage
                  << "," << p->corrected_voltage << "," << p->fallback << ",\"" << p->status << "\"," << p->model
                  << "\n";
        });
    mae = nh.subscribe<std_msgs::Float64>("/mm1/c/residual_mae", 10, [this](const std_msgs::Float64::ConstPtr& m) {
      mae_nm = m->data * 1e9;
      mae_stamp = ros::Time::now().toSec();
      if (on_mae) on_mae(mae_nm);
    });
    diag = nh.subscribe<diagnostic_msgs::DiagnosticArray>(
        "/diagnostics", 20, [this](const diagnostic_msgs::DiagnosticArray::ConstPtr& a) {
          for (const auto& s : a->status) {
            if (s.hardware_id == "piezo_predictor" && s.name.find("snapshot buffer") != std::string::npos) {
              snapshot_diag = s.message;
              for (const auto& kv : s.values)
                if (kv.key == "rings grown" || kv.key == "capacity [messages]") snapshot_diag += ", " + kv.key + " " + kv.value;
            }
            if (s.hardware_id != "piezo_predictor" || s.name.find("axis c") == std::string::npos) continue;
            diag_level = s.level;
            diag_message = s.message;
            if (s.level == diagnostic_msgs::DiagnosticStatus::WARN &&
                s.message.find("rolling free-run MAE") != std::string::npos && s.message.find("~snapshot") != std::string::npos)
              watch_warned = true;
          }
        });
  }

  // Spins until `done` (true) or `sim_s` of simulated time has passed (false); a wall limit guards a stalled clock.
  bool wait_for(const std::function<bool()>& done, double sim_s, double wall_s = 150.0) {
    const double end = ros::Time::now().toSec() + sim_s;
    const ros::WallTime wall_end = ros::WallTime::now() + ros::WallDuration(wall_s);
    while (ros::ok() && ros::WallTime::now() < wall_end && ros::Time::now().toSec() < end) {
      ros::spinOnce();
      if (done()) return true;
      ros::WallDuration(0.001).sleep();
    }
    return false;
  }
  // Spins for `sim_s` of simulated time; false when the wall limit came first (the clock stalled).
  bool spin_for(double sim_s, double wall_s = 150.0) {
    const double end = ros::Time::now().toSec() + sim_s;
    wait_for([] { return false; }, sim_s, wall_s);
    return ros::Time::now().toSec() >= end;
  }
  double now() const { return ros::Time::now().toSec(); }
};

std::string piezo_binary() {
  // the CLI is built next to this test executable (devel/lib/piezo_compensation)
  return (fs::read_symlink("/proc/self/exe").parent_path() / "piezo").string();
}

// Wall seconds since the test started (for reading a slow run).
struct WallClock {
  std::chrono::steady_clock::time_point start = std::chrono::steady_clock::now();
  double s() const { return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count(); }
};

// The rolling MAE a model that matches the device stays under: twice the noise floor.
constexpr double kThresholdNm = 2.0 * 16.8;

void check_clean_model(Loop& loop, double t_start, const WallClock& wall) {
  // (1) compensated with the clean model: the rolling MAE is under the threshold
  ASSERT_TRUE(loop.spin_for(150.0));
  ASSERT_TRUE(std::isfinite(loop.mae_nm)) << "no residual_mae published after 150 s";
  std::cout << "[live_loop] (1) clean model, " << loop.now() - t_start << " s simulated: rolling MAE "
            << loop.mae_nm << " nm (threshold " << kThresholdNm << " nm), diagnostics '" << loop.diag_message
            << "', wall " << wall.s() << " s\n";
  EXPECT_LT(loop.mae_nm, kThresholdNm) << "the clean model does not match the device before any effect";
  EXPECT_FALSE(loop.watch_warned) << loop.diag_message;
}

void switch_drift_on_until_warn(Loop& loop, double* t_on, const WallClock& wall) {
  // (2) the thermal drift is switched on: the watch warns on /diagnostics
  std_srvs::SetBool on;
  on.request.data = true;
  ASSERT_TRUE(ros::service::call("/mm1/mm3e_sim/set_thermal_drift", on));
  std::cout << "[live_loop] (2) " << on.response.message << "\n";
  *t_on = loop.now();
  ASSERT_TRUE(loop.wait_for([&] { return loop.watch_warned; }, 900.0)) << "no WARN within 900 s: " << loop.diag_message;
  std::cout << "[live_loop] (2) watch WARN " << loop.now() - *t_on << " s after the switch: '"
            << loop.diag_message << "', wall " << wall.s() << " s\n";
}

void take_snapshot(Loop& loop, double t_on, double snapshot_after_s, std::string* bag) {
  // (3) snapshot of the last 20 min with the effect on; `piezo residual` on it, base = the model running
  ASSERT_TRUE(loop.spin_for(std::max(0.0, t_on + snapshot_after_s - loop.now())));
  std_srvs::Trigger snap;
  ASSERT_TRUE(ros::service::call("/mm1/predictor/snapshot", snap));
  ASSERT_TRUE(snap.response.success) << snap.response.message;
  std::cout << "[live_loop] (3) snapshot: " << snap.response.message << "\n";
  // Lock-step (live_loop.test): the device waits for the predictor, so a stalled host costs no sample.
  EXPECT_EQ(snap.response.message.find(" gap"), std::string::npos) << "samples were lost in lock-step";
  *bag = snap.response.message.substr(0, snap.response.message.find(" ("));
}

// `piezo residual` on the snapshot, base = the model running: the effects it adds name the temperature.
void residual_names_temperature(Loop& loop, const std::string& bag, const std::string& clean,
                                const std::string& out_dir, const std::string& families,
                                const WallClock& wall) {
  fs::remove_all(out_dir);
  // Every family, the gain families included: the additive thermal effect must win against aux_gain on the same
  // signal (ResidualOptions::gain_margin; docs/validation/residual-loop.md, "Live loop"). The snapshot starts ~500 s into
  // the device's history: --mid-history fits the base's unknown initial creep state (without it the cold start
  // confounds the thermal term, and the loop adds time_gain and rate_dependent and makes TEST worse).
  std::vector<std::string> argv{piezo_binary(), "residual", "--data", bag, "--model", clean, "--axis", "c",
                                "--permutations", "200", "--mid-history", "--no-plots", "--out", out_dir};
  if (!families.empty()) argv.insert(argv.end(), {"--families", families});
  std::cout << "[live_loop] (3) " << piezo::util::command_line(argv) << "\n";
  std::atomic<bool> finished{false};
  piezo::util::ChildResult child;
  std::thread runner([&] {
    child = piezo::util::run_process(argv);
    finished = true;
  });
  loop.wait_for([&] { return finished.load(); }, 1e9, 120.0);  // the device keeps running meanwhile
  runner.join();
  ASSERT_TRUE(child.ok()) << child.error;
  const YAML::Node model = YAML::LoadFile(out_dir + "/model.yaml");
  ASSERT_EQ(model["kind"].as<std::string>(), "augmented");
  const YAML::Node terms = model["model"]["terms"];
  ASSERT_TRUE(terms && terms.size() > 0) << "piezo residual added no effect";
  const std::string family = terms[0]["family"].as<std::string>(), signal = terms[0]["signal"].as<std::string>();
  std::cout << "[live_loop] (3) first effect: " << family << " on " << signal << " (" << terms.size()
            << " term(s)), wall " << wall.s() << " s\n";
  EXPECT_TRUE(family == "aux_signal" || family == "aux_gain") << family;
  EXPECT_EQ(signal, "temperature_c");
  for (std::size_t i = 0; i < terms.size(); ++i)
    EXPECT_EQ(terms[i]["signal"].as<std::string>(), "temperature_c") << "term " << i << " names another cause";
}

void reload_recovers(Loop& loop, const std::string& out_dir) {
  // (4) ~model_file → the augmented model, ~reload_model: the rolling MAE comes back under the threshold
  ros::param::set("/mm1/predictor/model_file/c", out_dir + "/model.yaml");
  std_srvs::Trigger reload;
  ASSERT_TRUE(ros::service::call("/mm1/predictor/reload_model", reload));
  ASSERT_TRUE(reload.response.success) << reload.response.message;
  std::cout << "[live_loop] (4) " << reload.response.message << "\n";
  const double t_reload = loop.now();
  const double mae_before = loop.mae_nm;
  loop.mae_nm = std::nan("");
  // the watch starts again at a reload: the first figure comes after half a window; wait for a full one
  ASSERT_TRUE(loop.wait_for(
      [&] {
        return loop.now() > t_reload + 60.0 && loop.mae_stamp > t_reload + 60.0 &&
               loop.mae_nm < kThresholdNm && loop.diag_level == diagnostic_msgs::DiagnosticStatus::OK;
      },
      600.0))
      << "rolling MAE " << loop.mae_nm << " nm, diagnostics '" << loop.diag_message << "'";
  std::cout << "[live_loop] (4) reloaded; rolling MAE " << mae_before << " nm before, " << loop.mae_nm << " nm "
            << loop.now() - t_reload << " s after, diagnostics '" << loop.diag_message << "'\n";
}

void watch_stays_quiet(Loop& loop) {
  // and the watch stays quiet for another two windows (a WARN needs watch_hold_s above the threshold). Every
  // figure counts, in its callback: several that one spin delivers together (a loaded host) are several figures.
  double worst = loop.mae_nm, sum = 0.0;
  int n = 0;
  loop.watch_warned = false;
  loop.on_mae = [&](double mae_nm) {
    if (!std::isfinite(mae_nm)) return;
    worst = std::max(worst, mae_nm);
    sum += mae_nm;
    ++n;
  };
  loop.wait_for([] { return false; }, 120.0);
  loop.on_mae = nullptr;
  // The rolling MAE once rose again after the reload (mean 35–52 nm over these 120 s in some runs): the snapshot
  // bag was written stream by stream, reading it took 12.5 s, the reload stalled the callback thread for that
  // long (~4000 samples lost at 30×), and the base was warmed from rest. Now it stays near the floor (16.8 nm).
  if (loop.watch_warned) std::cout << "[live_loop] (4) the watch warned again after the reload: " << loop.diag_message << "\n";
  std::cout << "[live_loop] (4) rolling MAE over the next 120 s: mean " << (n ? sum / n : std::nan("")) << " nm, worst "
            << worst << " nm (" << n << " figures)\n";
  EXPECT_GT(n, 50) << "too few rolling-MAE figures after the reload";
  EXPECT_LT(worst, kThresholdNm) << "the rolling MAE rose above the watch threshold again after the reload";
  EXPECT_FALSE(loop.watch_warned) << loop.diag_message;
  std::cout << "[live_loop] snapshot buffer diagnostics: '" << loop.snapshot_diag << "'\n";
  EXPECT_FALSE(loop.snapshot_diag.empty()) << "no \"snapshot buffer\" status on /diagnostics";
}

}  // namespace

TEST(LiveLoop, WatchWarnsSnapshotResidualReloadRecovers) {
  ros::NodeHandle pnh("~");
  const std::string clean = pnh.param<std::string>("clean_model", "");
  const std::string out_dir = pnh.param<std::string>("out_dir", "/tmp/piezo_live_loop/residual");
  const double snapshot_after_s = pnh.param("snapshot_after_s", 1530.0);
  const std::string families = pnh.param<std::string>("families", "");  // "" = every family, gains included
  const WallClock wall;

  // The nodes start within seconds on an idle host; these return as soon as they are up.
  constexpr double kPatienceS = 60.0;
  ASSERT_TRUE(ros::service::waitForService("/mm1/predictor/snapshot", ros::Duration(kPatienceS)));
  ASSERT_TRUE(ros::service::waitForService("/mm1/predictor/reload_model", ros::Duration(kPatienceS)));
  ASSERT_TRUE(ros::service::waitForService("/mm1/mm3e_sim/set_thermal_drift", ros::Duration(kPatienceS)));
  ASSERT_TRUE(ros::Time::waitForValid(ros::WallDuration(kPatienceS)))
      << "no /clock from the simulated device";
  Loop loop;
  fs::create_directories(fs::path(out_dir).parent_path());
  loop.trace.open(fs::path(out_dir).parent_path() / "predictions_c.csv");
  loop.trace << "time_s,measured_nm,predicted_nm,intended_nm,commanded_v,corrected_v,fallback,status,model\n";
  ASSERT_TRUE(loop.wait_for([&] { return loop.readings > 20; }, 1e9, kPatienceS))
      << "no encoder readings of axis c";

  const double t_start = loop.now();
  ASSERT_NO_FATAL_FAILURE(check_clean_model(loop, t_start, wall));
  double t_on = 0.0;
  ASSERT_NO_FATAL_FAILURE(switch_drift_on_until_warn(loop, &t_on, wall));
  std::string bag;
  ASSERT_NO_FATAL_FAILURE(take_snapshot(loop, t_on, snapshot_after_s, &bag));
  ASSERT_NO_FATAL_FAILURE(residual_names_temperature(loop, bag, clean, out_dir, families, wall));
  ASSERT_NO_FATAL_FAILURE(reload_recovers(loop, out_dir));
  watch_stays_quiet(loop);
  std::cout << "[live_loop] total " << loop.now() - t_start << " s simulated, wall " << wall.s() << " s\n";
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "live_loop_check");
  ros::NodeHandle nh;
  return RUN_ALL_TESTS();
}
