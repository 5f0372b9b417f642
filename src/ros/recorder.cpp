#include "piezo_compensation/ros/recorder.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <limits>
#include <sstream>

#include <ros/master.h>
#include <std_msgs/String.h>

#include "piezo_compensation/ProtocolPhase.h"
#include "piezo_compensation/RecorderProgress.h"
#include "piezo_compensation/VoltageCommand.h"
#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/io/sequence_pairer.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/ros/interfaces.h"
#include "piezo_compensation/ros/params.h"

namespace fs = std::filesystem;

namespace piezo::ros_nodes {

namespace {

const auto by_sequence = [](const auto& msg) { return msg.sequence; };

YAML::Node to_yaml(const XmlRpc::XmlRpcValue& v) {
  XmlRpc::XmlRpcValue x = v;  // the accessors are non-const
  switch (x.getType()) {
    case XmlRpc::XmlRpcValue::TypeBoolean: return YAML::Node(static_cast<bool>(x));
    case XmlRpc::XmlRpcValue::TypeInt: return YAML::Node(static_cast<int>(x));
    case XmlRpc::XmlRpcValue::TypeDouble: return YAML::Node(static_cast<double>(x));
    case XmlRpc::XmlRpcValue::TypeString: return YAML::Node(static_cast<std::string>(x));
    case XmlRpc::XmlRpcValue::TypeArray: {
      YAML::Node n(YAML::NodeType::Sequence);
      for (int i = 0; i < x.size(); ++i) n.push_back(to_yaml(x[i]));
      return n;
    }
    case XmlRpc::XmlRpcValue::TypeStruct: {
      YAML::Node n(YAML::NodeType::Map);
      for (auto it = x.begin(); it != x.end(); ++it) n[it->first] = to_yaml(it->second);
      return n;
    }
    default: throw std::invalid_argument("unsupported parameter value type");
  }
}

std::size_t axis_index(const std::string& a) { return static_cast<std::size_t>(io::axis_index_or_none(a)); }

std::string join(const std::string& ns, const std::string& rel) { return ns + "/" + rel; }

}  // namespace

const params::NodeInterface& recorder_interface() {
  using namespace params;
  static const NodeInterface t = [] {
    const RecorderOptions d;
    constexpr double kDay = 86400.0;
    constexpr int kMaxInt = std::numeric_limits<int>::max();
    NodeInterface n;
    n.node = "piezo_recorder";
    n.summary = "drives a protocol through the driver's command topics into a chunked, resumable bag";
    n.params = {
        text("protocol", d.protocol,
             "noise, random_walk, sweep, creep, plan or sawtooth (required unless resuming an existing bag)"),
        structured("protocol_params", "", "map or YAML string", "{}",
                   "overrides of config/protocols.yaml for this protocol, e.g. {duration_s: 600.0}"),
        integer("seed", "", static_cast<int>(d.seed), 0, kMaxInt, "protocol seed (random walks, creep histories)"),
        number("sample_rate_hz", "Hz", d.sample_rate_hz, 0.01, 10000.0,
               "protocol rate; must equal the encoder rate: one command per sample"),
        number("duration_s", "s", d.duration_s, 0.0, 1e9, "record only the first duration_s of the protocol (0 = all)"),
        text("out", d.out, "the bag to write (must end in .bag)").rule("required"),
        flag("resume", d.resume, "continue the protocol where an interrupted `out` stopped"),
        texts("axes", d.axes, std::vector<std::string>(io::kAxisNames.begin(), io::kAxisNames.end()), 1, io::kAxisCount,
              "axes to drive and record"),
        number("chunk_period_s", "s", d.chunk_period_s, 0.001, kDay,
               "close the bag chunk this often (wall): at most this much is lost in a hard crash"),
        number("encoder_timeout_s", "s", d.encoder_timeout_s, 0.01, kDay,
               "no encoder data for this long (wall) = dead driver: stop (voltage held), close the bag"),
        number("startup_timeout_s", "s", d.startup_timeout_s, 0.01, kDay,
               "wait this long (wall) for the first encoder data on every axis"),
        number("min_free_space_mb", "MB", d.min_free_space_mb, 0.0, 1e9,
               "stop safely when the disk holding `out` has less free space than this"),
        number("voltage_tolerance_v", "V", d.voltage_tolerance_v, 0.0, 10.0,
               "applied within this of the command = the command has reached the piezo"),
        integer("max_wait_samples", "samples", d.max_wait_samples, 0, 1000,
                "encoder samples to wait for a command to show before recording anyway"),
        number("progress_period_s", "s", d.progress_period_s, 0.01, kDay, "a progress line in the log this often (wall)"),
        number("approach_timeout_s", "s", d.approach_timeout_s, 0.0, kDay,
               "wait this long (wall) for the driver to reach the first sample's voltages"),
        integer("stop_after_samples", "samples", static_cast<int>(d.stop_after_samples), 0, kMaxInt,
                "stop like Ctrl-C after this many samples in this session (0 = never)"),
    };
    using D = TopicDef::Direction;
    n.topics = {
        {"<axis>/command", "piezo_compensation/VoltageCommand", D::kPublishes, "the protocol's voltage [V], one per sample"},
        {"<axis>/encoder", "piezo_compensation/EncoderPosition", D::kSubscribes, "measured position (recorded)"},
        {"<axis>/voltage", "piezo_compensation/AxisVoltage", D::kSubscribes, "applied voltage (recorded)"},
        {"<axis>/true_position", "piezo_compensation/EncoderPosition", D::kSubscribes,
         "the simulated device's true position (recorded when present)"},
        {"protocol_phase", "piezo_compensation/ProtocolPhase", D::kPublishes, "segment and phase markers (latched)"},
        {"recorder/progress", "piezo_compensation/RecorderProgress", D::kPublishes, "samples done, ETA"},
    };
    return n;
  }();
  return t;
}

RecorderOptions RecorderOptions::from_params(const ros::NodeHandle& pnh, std::vector<std::string>* unknown) {
  RecorderOptions o;
  params::ParamReader r(pnh, recorder_interface());
  o.protocol = r.text("protocol");
  r.structured("protocol_params");
  if (pnh.hasParam("protocol_params")) {
    XmlRpc::XmlRpcValue v;
    pnh.getParam("protocol_params", v);
    try {
      if (v.getType() == XmlRpc::XmlRpcValue::TypeString)
        o.protocol_params = YAML::Load(static_cast<std::string>(v));  // also accept a YAML string
      else
        o.protocol_params = to_yaml(v);
    } catch (const std::exception& e) {
      throw std::invalid_argument("parameter " + r.resolved("protocol_params") + ": " + e.what());
    }
    if (!o.protocol_params.IsMap())
      throw std::invalid_argument("parameter " + r.resolved("protocol_params") + " must be a map");
  }
  o.seed = static_cast<std::uint64_t>(r.integer("seed"));
  o.sample_rate_hz = r.number("sample_rate_hz");
  o.duration_s = r.number("duration_s");
  o.out = r.text("out");
  o.resume = r.flag("resume");
  o.axes = r.texts("axes");
  o.chunk_period_s = r.number("chunk_period_s");
  o.encoder_timeout_s = r.number("encoder_timeout_s");
  o.startup_timeout_s = r.number("startup_timeout_s");
  o.min_free_space_mb = r.number("min_free_space_mb");
  o.voltage_tolerance_v = r.number("voltage_tolerance_v");
  o.max_wait_samples = r.integer("max_wait_samples");
  o.progress_period_s = r.number("progress_period_s");
  o.approach_timeout_s = r.number("approach_timeout_s");
  o.stop_after_samples = static_cast<std::uint64_t>(r.integer("stop_after_samples"));
  for (const char* gone : {"publish_clock", "lockstep_settle_s"}) {
    r.known(gone);
    if (pnh.hasParam(gone))
      throw std::invalid_argument(std::string("parameter ") + r.resolved(gone) +
                                  " is no longer a recorder parameter: lock-step with a simulated device is the "
                                  "driver's and mm3e_sim's ~sync_mode (record.launch lockstep:=true)");
  }
  if (unknown) *unknown = r.unknown();
  r.warn_unknown("piezo_recorder");
  o.validate();
  return o;
}

void RecorderOptions::validate() const {
  auto positive = [](double v, const char* name) {
    if (!(v > 0.0) || !std::isfinite(v)) throw std::invalid_argument(std::string("~") + name + " must be > 0");
  };
  if (out.empty()) throw std::invalid_argument("~out: give the bag to write (FILE.bag)");
  if (out.size() < 4 || out.compare(out.size() - 4, 4, ".bag") != 0)
    throw std::invalid_argument("~out must end in .bag, got '" + out + "'");
  if (protocol.empty() && !resume) throw std::invalid_argument("~protocol: give a protocol name");
  positive(sample_rate_hz, "sample_rate_hz");
  if (!(duration_s >= 0.0)) throw std::invalid_argument("~duration_s must be >= 0 (0 = whole protocol)");
  positive(chunk_period_s, "chunk_period_s");
  positive(encoder_timeout_s, "encoder_timeout_s");
  positive(startup_timeout_s, "startup_timeout_s");
  if (!(min_free_space_mb >= 0.0)) throw std::invalid_argument("~min_free_space_mb must be >= 0");
  if (!(voltage_tolerance_v >= 0.0)) throw std::invalid_argument("~voltage_tolerance_v must be >= 0");
  if (max_wait_samples < 0) throw std::invalid_argument("~max_wait_samples must be >= 0");
  positive(progress_period_s, "progress_period_s");
  if (!(approach_timeout_s >= 0.0)) throw std::invalid_argument("~approach_timeout_s must be >= 0");
  if (axes.empty()) throw std::invalid_argument("~axes: give at least one of " + io::axis_names_list());
  for (const auto& a : axes)
    if (io::axis_index_or_none(a) < 0) throw std::invalid_argument("~axes: unknown axis '" + a + "'");
}

void Recorder::parse_spec(const std::string& yaml, RecorderOptions& o, std::uint64_t& total, double& t0_s) {
  try {
    const YAML::Node n = YAML::Load(yaml);
    o.protocol = n["protocol"].as<std::string>();
    o.seed = n["seed"].as<std::uint64_t>();
    o.sample_rate_hz = n["sample_rate_hz"].as<double>();
    o.protocol_params = n["parameters"];
    total = n["samples"].as<std::uint64_t>();
    t0_s = n["t0_s"].as<double>();
  } catch (const YAML::Exception& e) {
    throw ros_io::RecorderBagError(std::string("protocol_phase marker: parameters_yaml is not a recorder spec (") +
                                   e.what() + ")");
  }
}

std::string Recorder::topic(const std::string& axis, const std::string& what) const {
  return ns_ + "/" + axis + "/" + what;
}

Recorder::Recorder(ros::NodeHandle nh, RecorderOptions options) : nh_(std::move(nh)), options_(std::move(options)) {
  options_.validate();
  ns_ = nh_.getNamespace();
  if (ns_ == "/") ns_.clear();

  bool resumed = false;
  if (options_.resume) {
    const auto found = ros_io::scan_recording(options_.out, topic(options_.axes.front(), "encoder"),
                                              join(ns_, "protocol_phase"));
    for (const auto& f : found.set_aside)
      ROS_WARN("recorder: %s was open or torn when the last session died (no index); its samples are recorded again",
               f.c_str());
    if (!found.set_aside.empty())
      ROS_WARN("recorder: resume drops %llu bytes in %zu unreadable chunk(s)",
               static_cast<unsigned long long>(found.set_aside_bytes), found.set_aside.size());
    if (found.duplicates > 0)
      ROS_WARN("recorder: %llu samples were both in %s and in its chunks (a merge cut short): kept once",
               static_cast<unsigned long long>(found.duplicates), options_.out.c_str());
    if (found.found && found.samples > 0) {
      const std::string wanted = options_.protocol;
      parse_spec(found.parameters_yaml, options_, total_, t0_s_);
      if (!wanted.empty() && wanted != options_.protocol)
        throw std::invalid_argument("~resume: " + options_.out + " holds protocol '" + options_.protocol +
                                    "', not '" + wanted + "'");
      next_ = found.next_sample;
      if (found.samples != found.next_sample)
        ROS_WARN("recorder: %s holds %llu samples but its last is %llu: the earlier data has gaps or repeats",
                 options_.out.c_str(), static_cast<unsigned long long>(found.samples),
                 static_cast<unsigned long long>(found.next_sample));
      resumed = true;
      ROS_INFO("recorder: resuming %s (protocol %s) at sample %llu of %llu", options_.out.c_str(),
               options_.protocol.c_str(), static_cast<unsigned long long>(next_),
               static_cast<unsigned long long>(total_));
    } else if (options_.protocol.empty()) {
      throw std::invalid_argument("~resume: " + options_.out + " holds no recording to resume; give ~protocol");
    }
  } else if (fs::exists(options_.out) || fs::exists(ros_io::parts_dir_of(options_.out))) {
    throw std::invalid_argument("~out: " + options_.out + " (or its .parts) exists; set ~resume to continue it");
  }

  protocol_ = protocols::make_protocol(options_.protocol, options_.protocol_params, options_.sample_rate_hz,
                                       options_.seed);
  if (!resumed) {
    const YAML::Node full = protocol_->parameters();  // the full set, so the bag alone regenerates it
    options_.protocol_params = full["parameters"] && full["parameters"].IsMap() ? full["parameters"] : full;
    total_ = protocol_->size();
    if (options_.duration_s > 0.0)
      total_ = std::min<std::uint64_t>(total_, static_cast<std::uint64_t>(
                                                   std::llround(options_.duration_s * options_.sample_rate_hz)));
  }
  if (total_ > protocol_->size())
    throw std::invalid_argument("~resume: the recording asks for more samples than protocol " + options_.protocol +
                                " has");
  first_of_session_ = next_;
  bag_ = std::make_unique<ros_io::ChunkedBag>(options_.out, options_.chunk_period_s, options_.min_free_space_mb);

  for (const auto& a : options_.axes) {
    axes_.emplace_back();
    axes_.back().name = a;
  }
  // small messages at the encoder rate: Nagle's algorithm would hold them back by up to tens of ms
  const ros::TransportHints hints = ros::TransportHints().tcpNoDelay();
  const params::NodeInterface& iface = recorder_interface();
  for (std::size_t k = 0; k < axes_.size(); ++k) {
    auto& ax = axes_[k];
    ax.command = nh_.advertise<piezo_compensation::VoltageCommand>(
        iface.topic_name<piezo_compensation::VoltageCommand>("<axis>/command", ax.name), 1);
    ax.encoder = nh_.subscribe<piezo_compensation::EncoderPosition>(
        iface.topic_name<piezo_compensation::EncoderPosition>("<axis>/encoder", ax.name), 100, [this, k](const piezo_compensation::EncoderPosition::ConstPtr& m) { on_encoder(k, m); },
        ros::VoidConstPtr(), hints);
    ax.voltage = nh_.subscribe<piezo_compensation::AxisVoltage>(
        iface.topic_name<piezo_compensation::AxisVoltage>("<axis>/voltage", ax.name), 100, [this, k](const piezo_compensation::AxisVoltage::ConstPtr& m) { on_voltage(k, m); },
        ros::VoidConstPtr(), hints);
    ax.truth = nh_.subscribe<piezo_compensation::EncoderPosition>(
        iface.topic_name<piezo_compensation::EncoderPosition>("<axis>/true_position", ax.name), 100,
        [this, k](const piezo_compensation::EncoderPosition::ConstPtr& m) { on_truth(k, m); }, ros::VoidConstPtr(),
        hints);
  }
  phase_pub_ = nh_.advertise<piezo_compensation::ProtocolPhase>(
      iface.topic_name<piezo_compensation::ProtocolPhase>("protocol_phase"), 10, true);
  progress_pub_ = nh_.advertise<piezo_compensation::RecorderProgress>(
      iface.topic_name<piezo_compensation::RecorderProgress>("recorder/progress"), 10);
  started_wall_ = last_encoder_wall_ = last_progress_log_ = last_progress_pub_ = Clock::now();
  watchdog_ = nh_.createWallTimer(ros::WallDuration(0.1), &Recorder::on_watchdog, this);
  ROS_INFO("recorder: protocol %s, %llu samples at %.3g Hz (%.1f h), into %s; waiting for encoder data",
           options_.protocol.c_str(), static_cast<unsigned long long>(total_), options_.sample_rate_hz,
           total_ / options_.sample_rate_hz / 3600.0, options_.out.c_str());
  if (next_ >= total_) finish(0, "the recording was already complete");
}

Recorder::~Recorder() {
  if (state_ != State::kDone) {
    try {
      finish(130, "recorder destroyed");
    } catch (...) {
    }
  }
}

ros::Time Recorder::stamp_of(std::uint64_t sample) const {
  return ros::Time(t0_s_ + static_cast<double>(sample) / options_.sample_rate_hz);
}

std::string Recorder::spec_yaml() const {
  YAML::Emitter e;
  YAML::Node n;
  n["protocol"] = options_.protocol;
  n["seed"] = options_.seed;
  n["sample_rate_hz"] = options_.sample_rate_hz;
  n["samples"] = total_;
  n["t0_s"] = t0_s_;
  n["parameters"] = options_.protocol_params;
  e << n;
  return e.c_str();
}

void Recorder::on_voltage(std::size_t k, const piezo_compensation::AxisVoltage::ConstPtr& msg) {
  auto& q = axes_[k].voltages;
  q.push_back(*msg);
  if (q.size() > 32) q.pop_front();
  if (std::all_of(axes_.begin(), axes_.end(), [](const AxisIo& a) { return a.pending.has_value(); }))
    row_ready();  // a reading was waiting for its voltage report
}

void Recorder::on_truth(std::size_t k, const piezo_compensation::EncoderPosition::ConstPtr& msg) {
  auto& q = axes_[k].truths;
  q.push_back(*msg);
  if (q.size() > 32) q.pop_front();
  if (waiting_truth_ && state_ == State::kRunning &&
             std::all_of(axes_.begin(), axes_.end(), [](const AxisIo& a) { return a.pending.has_value(); })) {
    complete_sample();  // a reading was waiting for its truth
  }
}

bool Recorder::data_ready_to_start() {
  for (const auto& a : axes_)
    if (a.tracker.received() < 3 || a.voltages.empty()) return false;
  if (!truth_checked_) {
    // a truth subscription may connect later than the encoder's (load): ask the master whether there is one,
    // so that either every row of the recording has the truth or none has
    truth_checked_ = true;
    ros::master::V_TopicInfo topics;
    if (ros::master::getTopics(topics))
      for (const auto& t : topics)
        for (const auto& a : axes_)
          if (t.name == topic(a.name, "true_position")) with_truth_ = true;
  }
  for (const auto& a : axes_)
    if (a.truth.getNumPublishers() > 0 || !a.truths.empty()) with_truth_ = true;
  if (with_truth_)
    for (const auto& a : axes_)
      if (a.truths.empty()) return false;
  return true;
}

void Recorder::on_encoder(std::size_t k, const piezo_compensation::EncoderPosition::ConstPtr& msg) {
  auto& ax = axes_[k];
  if (!msg->valid) {
    // a flagged reading is no measurement: never recorded, and it does not count as a live encoder either
    ROS_WARN_THROTTLE(5.0, "recorder: axis %s: encoder reading %u flagged invalid by the controller; skipped",
                      ax.name.c_str(), msg->sequence);
    return;
  }
  last_encoder_wall_ = Clock::now();
  const auto arrival = ax.tracker.add(msg->sequence);
  if (arrival == analysis::SequenceTracker::Arrival::kRestart ||
      (row_floor_sequence_ && static_cast<std::int32_t>(msg->sequence - *row_floor_sequence_) < -1000)) {
    // the controller restarted its counter (or the driver reconnected after a wrap): what is held belongs to
    // the old numbering and would never pair with the new readings
    ROS_WARN("recorder: axis %s: controller sequence restarted at %u; pairing starts again", ax.name.c_str(),
             msg->sequence);
    row_floor_sequence_.reset();
    last_row_sequence_.reset();
    for (auto& a : axes_) {
      a.readings.clear();
      a.voltages.clear();
      a.truths.clear();
      a.pending.reset();
    }
    waiting_truth_ = truth_wait_expired_ = false;
  }
  ax.readings.push_back(*msg);
  if (ax.readings.size() > 32) ax.readings.pop_front();
  if (arrival == analysis::SequenceTracker::Arrival::kGap || arrival == analysis::SequenceTracker::Arrival::kLate ||
      arrival == analysis::SequenceTracker::Arrival::kDuplicate)
    ROS_WARN_THROTTLE(5.0, "recorder: axis %s encoder sequence %u arrived %s", ax.name.c_str(), msg->sequence,
                      arrival == analysis::SequenceTracker::Arrival::kGap ? "after a gap (samples dropped)"
                                                                          : "out of order");
  if (state_ == State::kDone) return;
  if (state_ == State::kWaiting) {
    // a few readings and voltage reports on every axis, and the truth too where a simulated device publishes
    // it, so that every row of the recording has the same columns
    if (!data_ready_to_start()) return;
    state_ = State::kApproach;
    approach_started_ = Clock::now();
    ROS_INFO("recorder: data on all axes; moving to the voltages of sample %llu",
             static_cast<unsigned long long>(next_));
    publish_commands(protocol_->at(next_));
    return;
  }
  if (waiting_truth_) {
    // the next reading is here and the last one's truth is not: record that row with the newest truth
    truth_wait_expired_ = true;
    complete_sample();
    if (state_ != State::kRunning) return;
  }
  assemble_row();
}

void Recorder::row_ready() {
  if (state_ == State::kApproach)
    approach_step();
  else if (state_ == State::kRunning)
    complete_sample();
}

void Recorder::approach_step() {
  // the driver slew-limits: let it reach the first sample's voltages before recording starts; one command per
  // device sample, so the driver's command watchdog never holds half-way
  std::vector<const piezo_compensation::AxisVoltage*> volts;
  const VoltageMatch match = match_voltages(volts);
  if (match == VoltageMatch::kWaiting) return;  // a report is on its way (on_voltage comes back here)
  bool reached = match == VoltageMatch::kAll;   // a lost report: judge by the next sample
  for (std::size_t k = 0; k < axes_.size() && reached; ++k)
    if (!(std::fabs(volts[k]->voltage - axes_[k].commanded_v) <= options_.voltage_tolerance_v)) reached = false;
  const double waited_s = std::chrono::duration<double>(Clock::now() - approach_started_).count();
  if (!reached && waited_s < options_.approach_timeout_s) {
    publish_commands(protocol_->at(next_));
    return;
  }
  if (!reached)
    ROS_WARN("recorder: the applied voltages did not reach sample %llu's within ~approach_timeout_s = %.1f s; "
             "recording anyway", static_cast<unsigned long long>(next_), options_.approach_timeout_s);
  state_ = State::kRunning;
  if (next_ == 0) t0_s_ = std::max(ros::Time::now().toSec(), 1.0);  // bags need stamps > 0
  ROS_INFO("recorder: recording from sample %llu", static_cast<unsigned long long>(next_));
  send_sample();
}

void Recorder::assemble_row() {
  // The row is the first device sample after the command that every axis has a reading of. Pairing by the
  // controller's sequence keeps the axes of one row from one sample even when one axis' reading of an earlier
  // sample arrives after the command went out (otherwise that axis would stay one sample behind for good when
  // the device samples only on request).
  if (std::any_of(axes_.begin(), axes_.end(), [](const AxisIo& a) { return a.pending.has_value(); })) return;
  for (const auto& candidate : axes_.front().readings) {
    const std::uint32_t s = candidate.sequence;
    if (row_floor_sequence_ && static_cast<std::int32_t>(s - *row_floor_sequence_) < 0) continue;
    bool everywhere = true;
    for (const auto& ax : axes_)
      everywhere = everywhere && std::any_of(ax.readings.begin(), ax.readings.end(),
                                             [s](const auto& m) { return m.sequence == s; });
    if (!everywhere) continue;
    for (auto& ax : axes_)
      for (const auto& m : ax.readings)
        if (m.sequence == s) ax.pending = m;
    row_ready();
    return;
  }
}

void Recorder::send_sample() {
  try {
    send_sample_unchecked();
  } catch (const ros_io::RecorderBagError& e) {
    finish(1, e.what());
  }
}

void Recorder::publish_commands(const protocols::ProtocolSample& s) {
  // readings already here were taken before this command: the next row starts after the newest of them
  for (const auto& ax : axes_)
    for (const auto& m : ax.readings)
      if (!row_floor_sequence_ || static_cast<std::int32_t>(m.sequence + 1 - *row_floor_sequence_) > 0)
        row_floor_sequence_ = m.sequence + 1;
  const ros::Time now = ros::Time::now();
  for (auto& ax : axes_) {
    ax.commanded_v = s.voltage_v[axis_index(ax.name)];
    ax.pending.reset();
    piezo_compensation::VoltageCommand c;
    c.header.stamp = now;
    c.voltage = ax.commanded_v;
    ax.command.publish(c);
  }
}

void Recorder::send_sample_unchecked() {
  const protocols::ProtocolSample s = protocol_->at(next_);
  publish_commands(s);
  waited_samples_ = 0;
  waiting_truth_ = truth_wait_expired_ = false;
  if (!last_marker_ || next_ == first_of_session_ || last_marker_->segment != s.segment ||
      last_marker_->phase != s.phase)
    write_marker(s);
}

void Recorder::write_marker(const protocols::ProtocolSample& s) {
  piezo_compensation::ProtocolPhase m;
  m.header.stamp = stamp_of(next_);
  m.protocol = options_.protocol;
  m.phase = protocols::phase_name(s.phase);
  m.segment = static_cast<std::uint32_t>(s.segment);
  m.sample_index = next_;
  m.parameters_yaml = spec_yaml();
  bag_->write(join(ns_, "protocol_phase"), m.header.stamp, m);
  phase_pub_.publish(m);
  last_marker_ = s;
  ROS_INFO("recorder: sample %llu: segment %d, phase %s", static_cast<unsigned long long>(next_), s.segment,
           m.phase.c_str());
}

Recorder::VoltageMatch Recorder::match_voltages(std::vector<const piezo_compensation::AxisVoltage*>& volts) const {
  // each axis' applied voltage: the report with the reading's sequence number (the controller numbers both).
  // Reports travel on their own topic: wait for them unless a later one shows this one was lost.
  volts.assign(axes_.size(), nullptr);
  VoltageMatch result = VoltageMatch::kAll;
  for (std::size_t k = 0; k < axes_.size(); ++k) {
    const auto& ax = axes_[k];
    // the one pairing rule (io/sequence_pairer.h)
    const io::ReportMatch m = io::match_report(ax.voltages, ax.pending->sequence, false, by_sequence, &volts[k]);
    if (m == io::ReportMatch::kFound) continue;
    if (m == io::ReportMatch::kWaiting) return VoltageMatch::kWaiting;
    result = VoltageMatch::kLost;
    if (!volts[k]) volts[k] = &ax.voltages.back();
  }
  return result;
}

void Recorder::complete_sample() {
  std::vector<const piezo_compensation::AxisVoltage*> volts;
  if (match_voltages(volts) == VoltageMatch::kWaiting) return;
  bool applied = true;
  for (std::size_t k = 0; k < axes_.size(); ++k)
    if (!(std::fabs(volts[k]->voltage - axes_[k].commanded_v) <= options_.voltage_tolerance_v)) applied = false;
  if (!applied && waited_samples_ < options_.max_wait_samples) {
    // the command had not reached the piezo when this reading was taken: use the next one
    ++waited_samples_;
    // the same command again (the next row starts after this reading, as after any command): a device in
    // synchronous mode takes its next sample on it (on hardware it only refreshes the driver's watchdog)
    publish_commands(protocol_->at(next_));
    return;
  }
  if (with_truth_ && !truth_wait_expired_) {
    // the simulator publishes its truth directly, the reading comes through the driver: either may be first
    for (const auto& ax : axes_) {
      const piezo_compensation::EncoderPosition* t = nullptr;
      if (io::match_report(ax.truths, ax.pending->sequence, false, by_sequence, &t) == io::ReportMatch::kWaiting) {
        waiting_truth_ = true;
        return;
      }
    }
  }
  waiting_truth_ = truth_wait_expired_ = false;
  if (!applied) ++late_commands_;
  // device samples between two recorded rows: on simulated time each one stretches the real time behind a row
  const std::uint32_t seq0 = axes_.front().pending->sequence;
  if (last_row_sequence_ && recorded_in_session_ > 0) {
    const std::uint32_t d = seq0 - *last_row_sequence_;
    if (d > 1 && d < 100000) {
      skipped_device_samples_ += d - 1;
      ROS_WARN_THROTTLE(5.0, "recorder: %u device sample(s) passed unrecorded before sample %llu (waited %d)", d - 1,
                        static_cast<unsigned long long>(next_), waited_samples_);
    }
  }
  last_row_sequence_ = seq0;

  try {
    const ros::Time stamp = stamp_of(next_);
    const auto seq = static_cast<std::uint32_t>(next_);
    for (std::size_t k = 0; k < axes_.size(); ++k) {
      auto& ax = axes_[k];
      piezo_compensation::VoltageCommand c;
      c.header.stamp = stamp;
      c.header.seq = seq;
      c.voltage = ax.commanded_v;
      bag_->write(topic(ax.name, "command"), stamp, c);
      if (volts[k]) {
        piezo_compensation::AxisVoltage v = *volts[k];
        v.header.stamp = stamp;
        v.sequence = seq;
        bag_->write(topic(ax.name, "voltage"), stamp, v);
      }
      const piezo_compensation::EncoderPosition* truth = nullptr;
      // evaluation only: a late or lost truth message must not cost the row (every row needs one for the
      // reader): the one pairing rule takes the newest one before the reading, and it is counted
      if (with_truth_ && !ax.truths.empty() &&
          io::match_report(ax.truths, ax.pending->sequence, true, by_sequence, &truth) != io::ReportMatch::kFound) {
        ++substituted_truths_;
        if (!truth) truth = &ax.truths.back();
      }
      if (truth) {
        piezo_compensation::EncoderPosition t = *truth;
        t.header.stamp = stamp;
        t.sequence = seq;
        bag_->write(topic(ax.name, "true_position"), stamp, t);
      }
    }
    // encoders last: a sample whose first-axis encoder is in a closed chunk is complete
    for (std::size_t k = axes_.size(); k-- > 0;) {
      piezo_compensation::EncoderPosition e = *axes_[k].pending;
      e.header.stamp = stamp;
      e.sequence = seq;
      bag_->write(topic(axes_[k].name, "encoder"), stamp, e);
    }
    ++next_;
    ++recorded_in_session_;
    bag_->between_samples();
  } catch (const ros_io::RecorderBagError& e) {
    finish(1, e.what());
    return;
  }
  const auto now = Clock::now();
  rate_window_.emplace_back(now, next_);
  while (rate_window_.size() > 2 && now - rate_window_.front().first > std::chrono::seconds(30))
    rate_window_.pop_front();
  if (next_ >= total_) {
    finish(0, "protocol complete");
    return;
  }
  if (options_.stop_after_samples > 0 && recorded_in_session_ >= options_.stop_after_samples) {
    finish(130, "stopped after ~stop_after_samples = " + std::to_string(options_.stop_after_samples) + " samples");
    return;
  }
  if (now - last_progress_pub_ > std::chrono::seconds(1)) publish_progress(false);
  send_sample();
}

void Recorder::publish_progress(bool force_log) {
  const auto now = Clock::now();
  last_progress_pub_ = now;
  piezo_compensation::RecorderProgress p;
  p.header.stamp = ros::Time::now();
  p.protocol = options_.protocol;
  p.phase = last_marker_ ? protocols::phase_name(last_marker_->phase) : "waiting";
  p.sample_index = next_;
  p.total_samples = total_;
  p.percent = total_ ? 100.0 * static_cast<double>(next_) / static_cast<double>(total_) : 100.0;
  double per_s = 0.0;
  if (rate_window_.size() >= 2) {
    const double dt = std::chrono::duration<double>(rate_window_.back().first - rate_window_.front().first).count();
    if (dt > 0) per_s = (rate_window_.back().second - rate_window_.front().second) / dt;
  }
  p.eta = per_s > 0 ? static_cast<double>(total_ - next_) / per_s : std::numeric_limits<double>::quiet_NaN();
  std::uint64_t dropped = 0, ooo = 0;
  for (const auto& ax : axes_) {
    dropped += ax.tracker.dropped();
    ooo += ax.tracker.out_of_order();
  }
  p.dropped_samples = static_cast<std::uint32_t>(dropped);
  p.out_of_order_samples = static_cast<std::uint32_t>(ooo);
  progress_pub_.publish(p);
  if (state_ == State::kRunning) {
    try {
      bag_->write(join(ns_, "recorder/progress"), stamp_of(next_), p);
    } catch (const ros_io::RecorderBagError&) {
      // the next sample's write reports it
    }
  }
  if (force_log || now - last_progress_log_ > std::chrono::duration<double>(options_.progress_period_s)) {
    last_progress_log_ = now;
    ROS_INFO("recorder: %5.1f %%  sample %llu / %llu  phase %s  ETA %.0f s  dropped %llu  out of order %llu",
             p.percent, static_cast<unsigned long long>(next_), static_cast<unsigned long long>(total_),
             p.phase.c_str(), p.eta, static_cast<unsigned long long>(dropped), static_cast<unsigned long long>(ooo));
  }
}

void Recorder::on_watchdog(const ros::WallTimerEvent&) {
  if (state_ == State::kDone) return;
  const auto now = Clock::now();
  if (state_ == State::kWaiting) {
    if (std::chrono::duration<double>(now - started_wall_).count() > options_.startup_timeout_s)
      finish(1, "no encoder data on every axis within ~startup_timeout_s = " +
                    std::to_string(options_.startup_timeout_s) + " s (is the driver running?)");
    return;
  }
  if (std::chrono::duration<double>(now - last_encoder_wall_).count() > options_.encoder_timeout_s) {
    finish(1, "driver dead: no valid encoder data for more than ~encoder_timeout_s = " +
                  std::to_string(options_.encoder_timeout_s) + " s; voltage held at the last command");
    return;
  }
  if (now - last_progress_pub_ > std::chrono::seconds(1)) publish_progress(false);
}

void Recorder::request_stop(const std::string& why) {
  if (state_ != State::kDone) finish(130, why);
}

void Recorder::abandon() {
  if (state_ == State::kDone) return;
  state_ = State::kDone;
  exit_code_ = 1;
  failure_ = "abandoned (simulated crash)";
  watchdog_.stop();
  for (auto& ax : axes_) ax.encoder.shutdown();
  bag_->abandon();
  bag_.reset();
}

void Recorder::finish(int exit_code, const std::string& why) {
  if (state_ == State::kDone) return;
  state_ = State::kDone;
  exit_code_ = exit_code;
  watchdog_.stop();
  // no further commands: the driver holds the last applied voltage (never 0 V)
  for (auto& ax : axes_) {
    ax.encoder.shutdown();
    ax.voltage.shutdown();
    ax.truth.shutdown();
  }
  if (exit_code != 0) failure_ = why;
  publish_progress(true);

  summary_ = analysis::RecordingSummary{};
  std::uint64_t messages = 0;
  try {
    if (bag_) {
      std_msgs::String text;
      bool wrote_any = recorded_in_session_ > 0;
      if (wrote_any) {
        std::ostringstream os;
        os << "session ended at sample " << next_ << " of " << total_ << ": " << why;
        text.data = os.str();
        bag_->write(join(ns_, "recorder/log"), stamp_of(next_ > 0 ? next_ - 1 : 0), text);
      }
      messages = bag_->finish();
      bag_.reset();
    }
  } catch (const ros_io::RecorderBagError& e) {
    if (exit_code_ == 0) exit_code_ = 1;
    failure_ = failure_.empty() ? e.what() : failure_ + "; " + e.what();
    ROS_ERROR("recorder: %s", e.what());
  }
  // the summary reads the merged bag back, as fit and eval will
  try {
    if (messages > 0) {
      io::Dataset data = ros_io::read_data(options_.out);
      const io::Dataset program = protocol_->program(0, data.size());
      summary_ = analysis::summarize(data, options_.protocol, &program, options_.voltage_tolerance_v);
    }
  } catch (const std::exception& e) {
    const std::string what = std::string("reading ") + options_.out + " back failed: " + e.what();
    if (exit_code_ == 0) exit_code_ = 1;
    failure_ = failure_.empty() ? what : failure_ + "; " + what;
  }
  summary_.protocol = options_.protocol;
  for (const auto& ax : axes_) summary_.sequences.push_back(analysis::report_of(ax.name, ax.tracker));
  std::ostringstream os;
  os << analysis::format_summary(summary_) << "  commands that had not reached the piezo after "
     << options_.max_wait_samples << " samples: " << late_commands_ << "\n"
     << "  device samples that passed between recorded rows (time the rows do not show): "
     << skipped_device_samples_ << "\n"
     << "  rows whose true position was late or missing (newest earlier one used): " << substituted_truths_ << "\n";
  if (exit_code_ == 0) {
    ROS_INFO("recorder: done, %s: %s\n%s", why.c_str(), options_.out.c_str(), os.str().c_str());
  } else if (exit_code_ == 130) {
    ROS_WARN("recorder: %s at sample %llu of %llu; %s is valid, continue with ~resume:=true\n%s", why.c_str(),
             static_cast<unsigned long long>(next_), static_cast<unsigned long long>(total_), options_.out.c_str(),
             os.str().c_str());
  } else {
    ROS_ERROR("recorder: STOPPED: %s (sample %llu of %llu; what was recorded is in %s)\n%s", failure_.c_str(),
              static_cast<unsigned long long>(next_), static_cast<unsigned long long>(total_),
              options_.out.c_str(), os.str().c_str());
  }
}

}  // namespace piezo::ros_nodes

