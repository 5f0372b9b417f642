// Durability: the data of a file, then the directory entry that names it (after a rename), must reach the disk
// before anything that depends on them (a data file under its real name, deleting the chunks a merged bag holds).
#pragma once

#include <string>

namespace piezo::io {

// fsync of `path` (a directory when `directory`). "" on success, else the reason ("cannot open to sync: …",
// "fsync failed: …"); callers prefix the path and throw their own error type.
std::string fsync_path(const std::string& path, bool directory);

// fsync of the directory that holds `path` (the current directory for a bare file name).
std::string fsync_parent(const std::string& path);

}  // namespace piezo::io
