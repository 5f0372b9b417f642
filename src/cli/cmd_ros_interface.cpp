// `piezo ros-interface`: docs/ros_interface.md, generated from the nodes' interface tables (ros/interfaces.h: every
// parameter, topic and service as the node declares and uses it) and the launch files' <arg doc=...> attributes.
// --check FILE compares FILE with the generated text and names the first differing line (CTest
// ros_interface_drift). Either way it fails when a launch argument has no doc=, or when a parameter in a
// parameter template (a config/*.yaml a launch file loads into a node) is not in that node's table.
#include <tinyxml2.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cctype>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <optional>
#include <sstream>
#include <stdexcept>

#include "args.h"
#include "command.h"
#include "piezo_compensation/ros/interfaces.h"

namespace piezo::cli {
namespace {

namespace fs = std::filesystem;
using params::NodeInterface;

struct LaunchArg {
  std::string name, default_value, doc;
  bool required = false;
};

// A parameter template: a YAML file a launch file loads into a node.
struct Template {
  std::string node, file, launch;  // node type, path relative to the source tree, launch file name
};

// A value a launch file gives a node's parameter, with the launch file's own argument defaults, and where it comes
// from: a parameter template ("config/mm3e.yaml"), an argument ("driver.launch `interface`") or a literal <param>.
struct LaunchValue {
  std::string value, source;
};

// One <node> of a launch file: its type and what the launch file sets, by parameter name.
struct LaunchNode {
  std::string type;
  std::map<std::string, LaunchValue> values;
};

struct LaunchFile {
  std::string name, description;
  std::vector<LaunchArg> args;
  std::vector<Template> templates;
  std::vector<LaunchNode> nodes;
};

std::string collapse(const std::string& s) {
  std::string out;
  bool space = false;
  for (char c : s) {
    if (c == '\n' || c == '\t' || c == ' ') {
      space = !out.empty();
      continue;
    }
    if (space) out += ' ';
    space = false;
    out += c;
  }
  return out;
}

// Text for a table cell: no line breaks, pipes escaped; outside code, < and > as entities.
std::string cell(const std::string& s, bool code = false) {
  std::string out;
  for (char c : collapse(s)) {
    if (c == '|') out += "\\|";
    else if (!code && c == '<') out += "&lt;";
    else if (!code && c == '>') out += "&gt;";
    else out += c;
  }
  return code ? (out.empty() ? std::string("\"\"") : "`" + out + "`") : out;
}

using Defaults = std::map<std::string, std::string>;

// $(find piezo_compensation) and $(arg X) (X's default in the same file, resolved the same way); nothing when
// something else remains ($(eval ...), an unknown argument).
std::optional<std::string> expand(const std::string& s, const Defaults& defaults, int depth = 0) {
  std::string out = s;
  const std::string find = "$(find piezo_compensation)";
  for (auto at = out.find(find); at != std::string::npos; at = out.find(find)) out.replace(at, find.size(), ".");
  for (auto at = out.find("$(arg "); at != std::string::npos && depth < 8; at = out.find("$(arg ")) {
    const auto end = out.find(')', at);
    if (end == std::string::npos) return std::nullopt;
    const auto it = defaults.find(out.substr(at + 6, end - at - 6));
    if (it == defaults.end()) return std::nullopt;
    const auto inner = expand(it->second, defaults, depth + 1);
    if (!inner) return std::nullopt;
    out.replace(at, end - at + 1, *inner);
  }
  if (out.find("$(") != std::string::npos) return std::nullopt;
  return out.rfind("./", 0) == 0 ? out.substr(2) : out;
}

std::string resolve(const std::string& s, const Defaults& defaults) { return expand(s, defaults).value_or(""); }

// The argument a value is exactly ("$(arg X)" → X), else "".
std::string arg_of(const std::string& s) {
  const std::string t = collapse(s);
  if (t.rfind("$(arg ", 0) != 0 || t.back() != ')' || t.find(')') != t.size() - 1) return "";
  return t.substr(6, t.size() - 7);
}

// An if=/unless= condition under the file's defaults: "true"/"false" (also through $(arg X)) and
// $(eval arg('X') == '') or != ''; nothing for anything else.
std::optional<bool> condition(const std::string& expr, const Defaults& defaults) {
  if (const auto v = expand(expr, defaults)) {
    if (*v == "true" || *v == "1" || *v == "True") return true;
    if (*v == "false" || *v == "0" || *v == "False") return false;
    return std::nullopt;
  }
  const std::string t = collapse(expr);
  for (const char* op : {"') == '')", "') != '')"}) {
    const std::string head = "$(eval arg('";
    const auto at = t.find(op);
    if (t.rfind(head, 0) != 0 || at == std::string::npos || at + std::strlen(op) != t.size()) continue;
    const auto it = defaults.find(t.substr(head.size(), at - head.size()));
    if (it == defaults.end()) return std::nullopt;
    return (it->second.empty()) == (std::string(op) == "') == '')");
  }
  return std::nullopt;
}

// Whether an element's if=/unless= holds under the defaults; a label for when it does not ("sim:=true") or cannot be
// told ("when set"); nothing when the element is skipped for good.
std::optional<std::string> when(const tinyxml2::XMLElement* e, const Defaults& defaults) {
  for (const bool negate : {false, true}) {
    const char* expr = e->Attribute(negate ? "unless" : "if");
    if (!expr) continue;
    const auto c = condition(expr, defaults);
    if (!c) return std::string("when set");
    if (*c != negate) continue;
    const std::string a = arg_of(expr);
    if (a.empty()) return std::nullopt;
    return a + ":=" + (negate ? "false" : "true");
  }
  return std::string();
}

std::string flow(const YAML::Node& n) {
  if (n.IsScalar()) return n.as<std::string>();
  YAML::Emitter out;
  out << YAML::Flow << n;
  return out.c_str();
}

// Every key of a YAML map as a parameter name (a nested map's keys under "parent/"), into `values`.
void set_yaml(const YAML::Node& map, const std::string& prefix, const std::string& source,
              std::map<std::string, LaunchValue>& values) {
  for (const auto& kv : map) {
    const std::string name = prefix + kv.first.as<std::string>();
    values[name] = {flow(kv.second), source};
    if (kv.second.IsMap()) set_yaml(kv.second, name + "/", source, values);
  }
}

std::string labelled(const std::string& where, const std::string& label) {
  if (where.empty()) return label;
  return label.empty() ? where : where + ", " + label;
}

// Sources joined with "; ", the arguments of one launch file run together: "predictor.launch `a`, `b`".
void add_source(std::string& sources, const std::string& source) {
  if (sources.find(source) != std::string::npos) return;
  const auto tick = source.find(" `");
  const auto last = sources.rfind("; ") == std::string::npos ? 0 : sources.rfind("; ") + 2;
  std::string segment = sources.substr(last);  // the last source, without its run-together arguments
  for (auto at = segment.find(", `"); at != std::string::npos; at = segment.find(", `")) segment.erase(at, 2);
  if (tick != std::string::npos && source.find(',') == std::string::npos && segment.find(',') == std::string::npos &&
      segment.compare(0, tick + 2, source, 0, tick + 2) == 0) {
    sources += ", " + source.substr(tick + 1);
    return;
  }
  sources += (sources.empty() ? "" : "; ") + source;
}

// What one <node> sets, in document order (later settings win, as roslaunch applies them).
LaunchNode read_node(const tinyxml2::XMLElement* node, const Defaults& defaults, const std::string& label,
                     LaunchFile& lf, const fs::path& source) {
  LaunchNode ln{node->Attribute("type"), {}};
  for (const auto* c = node->FirstChildElement(); c; c = c->NextSiblingElement()) {
    const auto w = when(c, defaults);
    if (!w) continue;
    const std::string tag = c->Name(), here = labelled(lf.name, w->empty() ? label : labelled(label, *w));
    const char* name = c->Attribute("name");
    if (tag == "param" && name && c->Attribute("value")) {
      const std::string raw = c->Attribute("value"), arg = arg_of(raw);
      const auto v = expand(raw, defaults);
      ln.values[name] = {v ? *v : "(computed)", arg.empty() ? here : labelled(lf.name + " `" + arg + "`", label)};
      continue;
    }
    if (tag != "rosparam") continue;
    const char* cmd = c->Attribute("command");
    const char* file = c->Attribute("file");
    if (cmd && std::string(cmd) == "load" && file) {
      const std::string path = resolve(file, defaults);
      if (path.empty()) continue;
      lf.templates.push_back({ln.type, path, lf.name});
      try {
        const YAML::Node y = YAML::LoadFile((source / path).string());
        if (y.IsMap()) set_yaml(y, "", labelled(path, label), ln.values);
      } catch (const std::exception&) {
        // check_templates names a template that does not parse
      }
      continue;
    }
    const std::string text = c->GetText() ? c->GetText() : "", arg = arg_of(text);
    const auto v = expand(text, defaults);
    if (!v) continue;
    const std::string where = arg.empty() ? here : labelled(lf.name + " `" + arg + "`", label);
    if (const char* param = c->Attribute("param")) {
      ln.values[param] = {flow(YAML::Load(*v)), where};
      continue;
    }
    const YAML::Node y = YAML::Load(*v);
    if (y.IsMap()) set_yaml(y, "", where, ln.values);
  }
  return ln;
}

void find_nodes(const tinyxml2::XMLElement* e, const Defaults& defaults, const std::string& label, LaunchFile& lf,
                const fs::path& source) {
  for (const auto* c = e->FirstChildElement(); c; c = c->NextSiblingElement()) {
    const auto w = when(c, defaults);
    if (!w) continue;
    const std::string inner = w->empty() ? label : labelled(label, *w);
    if (std::string(c->Name()) == "node" && c->Attribute("type")) lf.nodes.push_back(read_node(c, defaults, inner, lf, source));
    else find_nodes(c, defaults, inner, lf, source);
  }
}

LaunchFile read_launch(const fs::path& path, const fs::path& source) {
  tinyxml2::XMLDocument doc;
  if (doc.LoadFile(path.c_str()) != tinyxml2::XML_SUCCESS)
    throw std::runtime_error(path.string() + ": not valid XML: " + doc.ErrorStr());
  LaunchFile lf;
  lf.name = path.filename().string();
  const tinyxml2::XMLElement* root = doc.FirstChildElement("launch");
  if (!root) throw std::runtime_error(path.string() + ": no <launch> element");
  // the description: the first comment before or at the top of <launch>
  const tinyxml2::XMLNode* starts[] = {doc.FirstChild(), root->FirstChild()};
  for (const tinyxml2::XMLNode* n : starts)
    for (; n && lf.description.empty(); n = n->NextSibling()) {
      if (n->ToComment()) lf.description = collapse(n->Value());
      if (n->ToElement()) break;
    }
  Defaults defaults;
  for (const auto* a = root->FirstChildElement("arg"); a; a = a->NextSiblingElement("arg")) {
    const char* name = a->Attribute("name");
    if (!name) throw std::runtime_error(path.string() + ": an <arg> without name=");
    if (a->Attribute("value")) continue;  // a constant of the file, not an argument
    LaunchArg arg;
    arg.name = name;
    arg.required = !a->Attribute("default");
    arg.default_value = arg.required ? "" : a->Attribute("default");
    if (!a->Attribute("doc"))
      throw std::runtime_error(path.string() + ": argument " + arg.name + " has no doc= (the reference lists it)");
    arg.doc = a->Attribute("doc");
    defaults[arg.name] = arg.default_value;
    lf.args.push_back(arg);
  }
  find_nodes(root, defaults, "", lf, source);
  return lf;
}

std::vector<LaunchFile> read_launch_files(const fs::path& source) {
  const fs::path dir = source / "launch";
  std::vector<fs::path> paths;
  for (const auto& e : fs::directory_iterator(dir))
    if (e.path().extension() == ".launch") paths.push_back(e.path());
  if (paths.empty()) throw std::runtime_error(dir.string() + ": no launch files");
  std::sort(paths.begin(), paths.end());
  std::vector<LaunchFile> out;
  for (const auto& p : paths) out.push_back(read_launch(p, source));
  return out;
}

// Every key of a template is a parameter of its node: a table entry, or a level of a name (protocol/…) under which
// each key is one. Throws naming the file, the key and the node.
void check_keys(const YAML::Node& map, const std::string& prefix, const NodeInterface& node, const Template& t) {
  for (const auto& kv : map) {
    const std::string name = prefix + kv.first.as<std::string>();
    bool declared = false, parent = false;
    for (const auto& p : node.params) {
      declared |= p.name == name;
      parent |= p.name.rfind(name + "/", 0) == 0;
    }
    if (declared) continue;
    if (parent && kv.second.IsMap()) {
      check_keys(kv.second, name + "/", node, t);
      continue;
    }
    throw std::runtime_error(t.file + " (loaded into " + t.node + " by launch/" + t.launch + "): parameter " + name +
                             " is not in the reference: declare it in " + t.node + "'s interface table");
  }
}

void check_templates(const std::vector<LaunchFile>& launches, const fs::path& source) {
  std::map<std::string, const NodeInterface*> nodes;
  for (const auto* n : node_interfaces()) nodes[n->node] = n;
  for (const auto& lf : launches)
    for (const auto& t : lf.templates) {
      const auto it = nodes.find(t.node);
      if (it == nodes.end())
        throw std::runtime_error("launch/" + lf.name + " loads " + t.file + " into " + t.node + ", which has no interface table");
      YAML::Node y;
      try {
        y = YAML::LoadFile((source / t.file).string());
      } catch (const std::exception& e) {
        throw std::runtime_error(t.file + " (launch/" + lf.name + "): " + e.what());
      }
      if (y.IsMap()) check_keys(y, "", *it->second, t);
    }
}

// The launch column of a parameter: each value the launch files that start the node give it, with where it comes
// from; "—" when none sets it (the code's default applies). A map parameter set key by key (model_file/a, ...) is
// shown as one map.
std::string launch_cell(const NodeInterface& n, const params::ParamDef& p, const std::vector<LaunchFile>& launches) {
  std::vector<std::pair<std::string, std::string>> found;  // value, sources
  auto add = [&](const std::string& value, const std::string& source) {
    for (auto& f : found)
      if (f.first == value) {
        add_source(f.second, source);
        return;
      }
    found.emplace_back(value, source);
  };
  for (const auto& lf : launches)
    for (const auto& ln : lf.nodes) {
      if (ln.type != n.node) continue;
      if (const auto it = ln.values.find(p.name); it != ln.values.end()) {
        add(it->second.value, it->second.source);
        continue;
      }
      std::string keys, sources;
      for (const auto& [name, v] : ln.values)
        if (name.rfind(p.name + "/", 0) == 0 && name.find('/', p.name.size() + 1) == std::string::npos) {
          keys += (keys.empty() ? "" : ", ") + name.substr(p.name.size() + 1) + ": " + v.value;
          add_source(sources, v.source);
        }
      if (!keys.empty()) add("{" + keys + "}", sources);
    }
  if (found.empty()) return "—";
  std::string out;
  for (const auto& [value, sources] : found) out += (out.empty() ? "" : "; ") + cell(value, true) + " (" + cell(sources) + ")";
  return out;
}

void write_params(std::ostream& os, const NodeInterface& n, const std::vector<LaunchFile>& launches) {
  std::map<std::string, std::string> why;
  for (const auto& s : standard_params())
    if (s.node == n.node) why[s.name] = s.why;
  for (const bool standard : {true, false}) {
    std::size_t count = 0;
    for (const auto& p : n.params) count += why.count(p.name) == (standard ? 1u : 0u);
    if (count == 0) continue;
    os << "\n### " << (standard ? "Standard parameters" : "Advanced parameters") << " (" << count << ")\n\n"
       << "| parameter | type | unit | default (code) | default (launch) | valid range | meaning |"
       << (standard ? " why set it |\n|---|---|---|---|---|---|---|---|\n" : "\n|---|---|---|---|---|---|---|\n");
    for (const auto& p : n.params) {
      if (why.count(p.name) != (standard ? 1u : 0u)) continue;
      os << "| " << cell("~" + p.name, true) << " | " << cell(p.type_name()) << " | " << cell(p.unit) << " | "
         << cell(p.default_string(), p.default_string().rfind('(', 0) != 0) << " | " << launch_cell(n, p, launches)
         << " | " << cell(p.range_string()) << " | " << cell(p.meaning) << " |";
      if (standard) os << " " << cell(why[p.name]) << " |";
      os << "\n";
    }
  }
  os << "\n";
}

void write_node(std::ostream& os, const NodeInterface& n, const std::vector<std::string>& templates,
                const std::vector<LaunchFile>& launches) {
  std::string summary = cell(n.summary);
  if (!summary.empty()) summary[0] = static_cast<char>(std::toupper(static_cast<unsigned char>(summary[0])));
  os << "## " << n.node << "\n\n" << summary << ".";
  if (!templates.empty()) {
    os << " Parameter template" << (templates.size() > 1 ? "s" : "") << ":";
    for (std::size_t i = 0; i < templates.size(); ++i) os << (i ? ", " : " ") << "`" << templates[i] << "`";
    os << ".";
  }
  os << "\n\n### Topics\n\n| topic | type | direction | meaning |\n|---|---|---|---|\n";
  for (const auto& t : n.topics)
    os << "| " << cell(t.name, true) << " | `" << t.type << "` | "
       << (t.direction == params::TopicDef::Direction::kPublishes ? "publishes" : "subscribes") << " | "
       << cell(t.meaning) << " |\n";
  for (const bool called : {false, true}) {
    std::vector<const params::ServiceDef*> list;
    for (const auto& s : n.services)
      if (s.called == called) list.push_back(&s);
    if (list.empty()) continue;
    os << "\n### " << (called ? "Services called" : "Services") << "\n\n| service | type | meaning |\n|---|---|---|\n";
    for (const auto* s : list) os << "| " << cell(s->name, true) << " | `" << s->type << "` | " << cell(s->meaning) << " |\n";
  }
  write_params(os, n, launches);
}

// A standard parameter no node declares would vanish from the reference silently.
void check_standard() {
  for (const auto& s : standard_params()) {
    const NodeInterface* node = nullptr;
    for (const auto* n : node_interfaces())
      if (n->node == s.node) node = n;
    bool declared = false;
    for (const auto& p : node ? node->params : std::vector<params::ParamDef>{}) declared |= p.name == s.name;
    if (!declared)
      throw std::runtime_error("standard parameter " + s.node + " ~" + s.name +
                               " (src/ros/interfaces.cpp) is not in that node's interface table");
  }
}

void write_launch(std::ostream& os, const LaunchFile& lf) {
  os << "### " << lf.name << "\n\n";
  if (!lf.description.empty()) os << cell(lf.description) << "\n\n";
  os << "| argument | default | meaning |\n|---|---|---|\n";
  for (const auto& a : lf.args)
    os << "| `" << a.name << "` | " << (a.required ? std::string("(required)") : cell(a.default_value, true)) << " | "
       << cell(a.doc) << " |\n";
  os << "\n";
}

std::string generate(const std::vector<LaunchFile>& launches) {
  std::map<std::string, std::vector<std::string>> templates;  // node → files
  for (const auto& lf : launches)
    for (const auto& t : lf.templates) {
      auto& v = templates[t.node];
      if (std::find(v.begin(), v.end(), t.file) == v.end()) v.push_back(t.file);
    }
  std::size_t n_params = 0, n_args = 0;
  for (const auto* n : node_interfaces()) n_params += n->params.size();
  for (const auto& lf : launches) n_args += lf.args.size();
  std::ostringstream os;
  os << "# ROS interface\n\n"
     << "Every node's topics, services and parameters, and every launch file's arguments: " << n_params
     << " parameters of " << node_interfaces().size() << " nodes, " << n_args << " arguments of " << launches.size()
     << " launch files.\n"
     << "Generated by `scripts/gen-ros-interface` (`piezo ros-interface`) from the interface table each node reads its\n"
     << "parameters and names its topics through (`src/ros/`, `ros/params.h`) and from the launch files' `doc=`\n"
     << "attributes; do not edit it by hand. The CTest `ros_interface_drift` fails when it differs from them, or when a\n"
     << "parameter of a template in `config/` is not listed here.\n\n"
     << "Names are relative to the manipulator's namespace (`/mm1`, ...); `<axis>` is a, b or c; `~` is the node's\n"
     << "private namespace. Messages carry SI units (m, s, V); every parameter is validated at start-up, and a value of\n"
     << "the wrong type or outside its range stops the node with one line naming it.\n\n"
     << "Each node's parameters come in two tables. **Standard**: what an operator sets for a rig, each with why.\n"
     << "**Advanced**: tuning and test settings whose defaults suit the MM3E. *default (code)* is what the node uses\n"
     << "when nothing sets the parameter; *default (launch)* is what the launch files that start the node set it to with\n"
     << "their own argument defaults, and where from (a template in `config/`, a launch argument, or a literal; a\n"
     << "condition such as `sim:=true` when only a non-default argument sets it); — when no launch file sets it.\n"
     << "Launch files that include others pass their own arguments down (see Launch files).\n\n## Nodes\n\n";
  for (const auto* n : node_interfaces()) os << "- [" << n->node << "](#" << n->node << "): " << cell(n->summary) << "\n";
  os << "- [Launch files](#launch-files)\n\n";
  for (const auto* n : node_interfaces()) write_node(os, *n, templates[n->node], launches);
  os << "## Launch files\n\n`roslaunch piezo_compensation FILE name:=value ...`; "
     << "`roslaunch --ros-args piezo_compensation FILE` lists the same.\n\n";
  for (const auto& lf : launches) write_launch(os, lf);
  std::string text = os.str();
  text.pop_back();  // one newline at the end
  return text;
}

std::vector<std::string> lines_of(const std::string& text) {
  std::vector<std::string> out;
  std::istringstream in(text);
  for (std::string l; std::getline(in, l);) out.push_back(l);
  return out;
}

// 0 when `path` holds `generated`; else names the first differing line.
int check(const std::string& path, const std::string& generated) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error(path + ": cannot open (write it with scripts/gen-ros-interface)");
  std::stringstream buf;
  buf << in.rdbuf();
  const auto have = lines_of(buf.str()), want = lines_of(generated);
  for (std::size_t i = 0; i < std::max(have.size(), want.size()); ++i) {
    const std::string h = i < have.size() ? have[i] : "(end of file)", w = i < want.size() ? want[i] : "(end)";
    if (h == w) continue;
    std::cerr << path << ":" << i + 1 << ": differs from the interface tables and launch files\n  file:      " << h
              << "\n  generated: " << w << "\nrun scripts/gen-ros-interface to regenerate it\n";
    return 1;
  }
  return 0;
}

int run(int argc, char** argv) {
  Args args("ros-interface",
            "Write the ROS interface reference (docs/ros_interface.md) from the nodes' interface tables and the\n"
            "launch files' doc= attributes, or check that FILE is up to date. Fails when a launch argument has no\n"
            "doc= or a parameter template in config/ holds a parameter its node does not declare.");
  args.option("source-dir", "DIR", "the package's source tree (launch/, config/)", PIEZO_SOURCE_DIR_FALLBACK)
      .option("out", "FILE", "write the reference here (default: standard output)")
      .option("check", "FILE", "compare FILE with the generated reference; exit 1 naming the first differing line");
  if (!args.parse(argc, argv)) return 0;
  const fs::path source = args.str("source-dir");
  const auto launches = read_launch_files(source);
  check_templates(launches, source);
  check_standard();
  const std::string text = generate(launches);
  if (args.has("check")) return check(args.str("check"), text);
  if (!args.has("out")) {
    std::cout << text;
    return 0;
  }
  std::ofstream out(args.str("out"));
  if (!(out << text)) throw std::runtime_error(args.str("out") + ": cannot write");
  return 0;
}

const Register reg("ros-interface", "write or check docs/ros_interface.md (every node's parameters, topics, services)",
                   run);
}  // namespace
}  // namespace piezo::cli
