// The NanoControl transport's parameters (docs/nanocontrol.md) for mm3e_driver and mm3e_sim, read through the
// parameter layer, and the driver's "nanocontrol" diagnostics status.
#pragma once

#include <diagnostic_updater/diagnostic_updater.h>

#include <vector>

#include "piezo_compensation/nanocontrol/sim_device.h"
#include "piezo_compensation/nanocontrol/transport.h"
#include "piezo_compensation/ros/params.h"

namespace piezo::mm3e {

// ~port, ~baud, ~reply_timeout_s, ~channels, ~nm_per_count, ~counts_per_volt, ~counter_reads, ~min_sample_period_s.
std::vector<params::ParamDef> nanocontrol_driver_params();
// ~port (the link the pseudo-terminal appears at), ~channels, ~nm_per_count, ~counts_per_volt, ~reply_delay_s.
std::vector<params::ParamDef> nanocontrol_sim_params();

// Reads them; with `check` (transport nanocontrol) also the rules between them and the voltage limits, each
// error naming the parameter.
nanocontrol::LinkOptions read_link_options(params::ParamReader& r, double min_voltage_v, double max_voltage_v, bool check);
nanocontrol::SimDeviceConfig read_sim_device(params::ParamReader& r, double initial_voltage_v);

// previous: the counters at the last update; a fault counted since then raises WARN naming it, a latched breakdown
// ERROR.
void diagnose_link(const nanocontrol::LinkMonitor::Snapshot& s, const nanocontrol::LinkCounters& previous,
                   diagnostic_updater::DiagnosticStatusWrapper& stat);

}  // namespace piezo::mm3e
