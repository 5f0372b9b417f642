#include "plot_script.h"

#include <cstdlib>
#include <iostream>
#include <stdexcept>

#include "piezo_compensation/util/child_process.h"

namespace piezo::cli {

namespace fs = std::filesystem;

fs::path find_package_file(const std::string& relative) {
  std::vector<fs::path> roots;
  if (const char* src = std::getenv("PIEZO_SOURCE_DIR"); src && *src) roots.emplace_back(src);
  std::error_code ec;
  const fs::path exe = fs::read_symlink("/proc/self/exe", ec);
  if (!ec) roots.push_back(exe.parent_path().parent_path().parent_path() / "share" / "piezo_compensation");
  roots.emplace_back(PIEZO_INSTALL_SHARE_DIR);
  roots.emplace_back(PIEZO_SOURCE_DIR_FALLBACK);
  std::string looked;
  for (const fs::path& root : roots) {
    if (!root.is_absolute()) continue;  // a relative root would depend on the current directory
    const fs::path p = root / relative;
    if (fs::is_regular_file(p, ec)) return p;
    looked += (looked.empty() ? "" : ", ") + p.string();
  }
  throw std::runtime_error(relative + " not found (looked in " + looked + "; set PIEZO_SOURCE_DIR)");
}

fs::path find_plot_script(const std::string& name) { return find_package_file("scripts/plotting/" + name); }

bool run_plot_script(const std::string& what, const std::string& name, const std::vector<std::string>& args) {
  std::vector<std::string> argv{"/usr/bin/python3"};
  try {
    argv.push_back(find_plot_script(name).string());
  } catch (const std::exception& e) {
    std::cerr << what << ": plotting failed (" << e.what() << "); the reports are written\n";
    return false;
  }
  argv.insert(argv.end(), args.begin(), args.end());
  const util::ChildResult r = util::run_process(argv);
  if (r.ok()) return true;
  std::cerr << what << ": plotting failed (" << util::command_line(argv) << ": " << r.error
            << "); the reports are written\n";
  return false;
}

}  // namespace piezo::cli
