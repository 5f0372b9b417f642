// The package's own files (the matplotlib writers in scripts/plotting/, config/), found in the source tree or the install space (never relative to
// the current directory) and started with an argument vector (no shell).
#pragma once

#include <filesystem>
#include <string>
#include <vector>

namespace piezo::cli {

// <relative> (e.g. "config/simulator.yaml") under, in order: $PIEZO_SOURCE_DIR, the install space of this executable
// (<prefix>/lib/piezo_compensation/piezo → <prefix>/share/piezo_compensation), the install prefix it was built for,
// the source tree it was built from. Throws std::runtime_error naming every place looked in.
std::filesystem::path find_package_file(const std::string& relative);

// find_package_file("scripts/plotting/" + name).
std::filesystem::path find_plot_script(const std::string& name);

// /usr/bin/python3 <script> <args...>. On failure prints "<what>: plotting failed (...)" to stderr and returns false.
bool run_plot_script(const std::string& what, const std::string& name, const std::vector<std::string>& args);

}  // namespace piezo::cli
