// Every command-line tool of the suite (src/tools/*.cpp) and every script (scripts/) answers
// --help with its usage on stdout and exit status 0.
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

namespace fs = std::filesystem;

namespace {

struct Outcome {
  int status = -1;
  std::string out;
};

/// Runs `command` (stderr discarded), its stdout and exit status.
Outcome run(const std::string& command) {
  Outcome r;
  FILE* pipe = popen((command + " 2>/dev/null").c_str(), "r");
  if (!pipe)
    return r;
  std::array<char, 4096> buffer{};
  std::size_t n = 0;
  while ((n = fread(buffer.data(), 1, buffer.size(), pipe)) > 0)
    r.out.append(buffer.data(), n);
  const int status = pclose(pipe);
  r.status = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

/// The folder the tools are built into: beside this test's executable, else the source tree's
/// default build folder.
fs::path toolDir() {
  std::error_code ec;
  const fs::path self = fs::read_symlink("/proc/self/exe", ec).parent_path();
  if (!ec && fs::exists(self / "track_frames"))
    return self;
  return fs::path(NG_SOURCE_DIR) / "build/devel/lib/needle_guidance";
}

void expectHelp(const std::string& name, const std::string& command) {
  const Outcome r = run(command + " --help");
  EXPECT_EQ(r.status, 0) << name << " --help exited " << r.status;
  EXPECT_NE(r.out.find("usage"), std::string::npos) << name << " --help printed: " << r.out;
}

TEST(CommandLineHelp, EveryToolPrintsItsUsageAndExitsZero) {
  const fs::path dir = toolDir();
  int tools = 0;
  for (const auto& e : fs::directory_iterator(fs::path(NG_SOURCE_DIR) / "src/tools")) {
    if (e.path().extension() != ".cpp")
      continue;
    const std::string name = e.path().stem().string();
    ASSERT_TRUE(fs::exists(dir / name)) << "tool " << name << " not built in " << dir;
    expectHelp(name, (dir / name).string());
    ++tools;
  }
  EXPECT_GE(tools, 10);
}

TEST(CommandLineHelp, EveryScriptPrintsItsUsageAndExitsZero) {
  const fs::path scripts = fs::path(NG_SOURCE_DIR) / "scripts";
  for (const std::string name : {"bench", "demo", "test"})
    expectHelp(name, (scripts / name).string());
  for (const auto& e : fs::directory_iterator(scripts)) {
    if (e.path().extension() == ".py")
      expectHelp(e.path().filename().string(), "/usr/bin/python3 " + e.path().string());
  }
}

TEST(CommandLineHelp, TrackFramesRefusesABadPriorNamingIt) {
  const fs::path tool = toolDir() / "track_frames";
  const Outcome r = run(tool.string() + " --frames /tmp --out /tmp/x.csv --entry-point 12");
  EXPECT_EQ(r.status, 2);
  const Outcome angle = run(tool.string() + " --frames /tmp --out /tmp/x.csv --entry-angle steep");
  EXPECT_EQ(angle.status, 2);
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
