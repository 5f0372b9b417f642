#include "piezo_compensation/util/progress_bar.h"

#include <cmath>
#include <cstdio>
#include <ostream>

namespace piezo::util {

ProgressBar::ProgressBar(std::ostream& os, std::string unit, bool enabled)
    : os_(os), unit_(std::move(unit)), enabled_(enabled) {
  start_ = last_draw_ = phase_start_ = std::chrono::steady_clock::now();
}

ProgressBar::~ProgressBar() {
  if (!finished_) finish();
}

std::string ProgressBar::format_duration(double s) {
  char buf[64];
  if (!std::isfinite(s) || s < 0) return "?";
  if (s < 60) std::snprintf(buf, sizeof buf, "%.1f s", s);
  else if (s < 3600) std::snprintf(buf, sizeof buf, "%d min %02d s", int(s / 60), int(s) % 60);
  else std::snprintf(buf, sizeof buf, "%d h %02d min", int(s / 3600), int(s / 60) % 60);
  return buf;
}

void ProgressBar::update(double done, double total, const std::string& what) {
  if (!enabled_) return;
  if (what != what_) {  // a new phase restarts the ETA clock
    if (!what_.empty()) draw(true), os_ << "\n";
    what_ = what;
    phase_start_ = std::chrono::steady_clock::now();
  }
  last_done_ = done;
  last_total_ = total;
  draw(false);
}

void ProgressBar::draw(bool force) {
  const auto now = std::chrono::steady_clock::now();
  if (!force && now - last_draw_ < std::chrono::milliseconds(200) && last_done_ < last_total_) return;
  last_draw_ = now;
  const double el = std::chrono::duration<double>(now - phase_start_).count();
  char line[256];
  if (last_total_ > 0) {
    const double f = std::min(1.0, std::max(0.0, last_done_ / last_total_));
    const int width = 24, fill = static_cast<int>(f * width);
    std::string bar(fill, '#');
    bar += std::string(width - fill, '.');
    const double eta = f > 0 ? el * (1 - f) / f : NAN;
    std::snprintf(line, sizeof line, "\r%s [%s] %3.0f%% %.0f/%.0f %s, %.3g %s/s, ETA %s   ", what_.c_str(),
                  bar.c_str(), 100 * f, last_done_, last_total_, unit_.c_str(), el > 0 ? last_done_ / el : 0.0,
                  unit_.c_str(), format_duration(eta).c_str());
  } else {
    std::snprintf(line, sizeof line, "\r%s %.0f %s, %s elapsed   ", what_.c_str(), last_done_, unit_.c_str(),
                  format_duration(el).c_str());
  }
  os_ << line << std::flush;
}

void ProgressBar::finish() {
  if (finished_) return;
  finished_ = true;
  if (!enabled_ || what_.empty()) return;
  draw(true);
  const double el = std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
  os_ << "\ndone in " << format_duration(el) << "\n" << std::flush;
}

}  // namespace piezo::util
