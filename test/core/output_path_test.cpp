// Report folders and journal files: system locations and files the suite did not make are
// refused, with the parameter and the path named, and nothing is created.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <functional>
#include <string>

#include "needle_guidance/report/output_path.h"

namespace {
namespace fs = std::filesystem;
using needle_guidance::report::checkAppendFile;
using needle_guidance::report::kReportMarker;
using needle_guidance::report::prepareReportDir;
using needle_guidance::report::systemLocation;

fs::path scratch(const std::string& name) {
  const fs::path p = fs::temp_directory_path() / ("ng_output_path_test_" + name);
  fs::remove_all(p);
  return p;
}

std::string refusal(const std::function<void()>& f) {
  try {
    f();
  } catch (const std::exception& e) {
    return e.what();
  }
  return "";
}

TEST(OutputPath, SystemLocationsAreNamed) {
  EXPECT_NE(systemLocation("/etc/passwd"), "");
  EXPECT_NE(systemLocation("/usr/lib/x"), "");
  EXPECT_NE(systemLocation("/tmp/../etc/cron.d/job"), "") << "normalised before the check";
  EXPECT_NE(systemLocation("/"), "");
  EXPECT_NE(systemLocation("/var/log/x"), "");
  EXPECT_EQ(systemLocation("/var/tmp/report"), "");
  EXPECT_EQ(systemLocation("/tmp/report"), "");
  EXPECT_EQ(systemLocation("/root/.ros/reports/x"), "");
  EXPECT_EQ(systemLocation("/etcetera/x"), "") << "a prefix of a name is not the folder";
}

TEST(OutputPath, ReportDirIsCreatedWithItsMarkerAndReused) {
  const fs::path dir = scratch("new") / "a" / "b";
  ASSERT_EQ(refusal([&] { prepareReportDir(dir.string(), "~report_dir", false); }), "");
  EXPECT_TRUE(fs::exists(dir / kReportMarker));
  std::ofstream(dir / "summary.json") << "{}";
  EXPECT_EQ(refusal([&] { prepareReportDir(dir.string(), "~report_dir", false); }), "")
      << "a folder the suite made is written again";
}

TEST(OutputPath, ReportDirHoldingOnlyEmptyFoldersIsAccepted) {
  // The afterloader of the same launch may create its journal folder inside the report first.
  const fs::path dir = scratch("journal_first");
  fs::create_directories(dir / "journal" / "nested");
  ASSERT_EQ(refusal([&] { prepareReportDir(dir.string(), "~report_dir", false); }), "");
  EXPECT_TRUE(fs::exists(dir / kReportMarker));

  const fs::path foreign = scratch("foreign_nested");
  fs::create_directories(foreign / "journal");
  std::ofstream(foreign / "journal" / "notes.txt") << "precious";
  EXPECT_NE(refusal([&] { prepareReportDir(foreign.string(), "~report_dir", false); }), "")
      << "a file at any depth makes the folder someone else's";
  EXPECT_FALSE(fs::exists(foreign / kReportMarker));
}

TEST(OutputPath, ForeignSystemAndFileTargetsAreRefusedAndNothingIsCreated) {
  const fs::path foreign = scratch("foreign");
  fs::create_directories(foreign);
  std::ofstream(foreign / "thesis.tex") << "precious";
  const std::string why =
      refusal([&] { prepareReportDir(foreign.string(), "~report_dir", false); });
  EXPECT_NE(why.find("~report_dir"), std::string::npos) << why;
  EXPECT_NE(why.find(foreign.string()), std::string::npos) << why;
  EXPECT_FALSE(fs::exists(foreign / kReportMarker));

  const std::string sys = refusal([] { prepareReportDir("/etc/ng_report", "~report_dir", false); });
  EXPECT_NE(sys.find("/etc"), std::string::npos) << sys;
  EXPECT_FALSE(fs::exists("/etc/ng_report"));

  const fs::path file = scratch("file");
  std::ofstream(file) << "x";
  EXPECT_NE(refusal([&] { prepareReportDir(file.string(), "~report_dir", false); }), "");
  EXPECT_NE(refusal([] { prepareReportDir("", "~report_dir", false); }), "");
}

TEST(OutputPath, JournalFilesMustBeOurs) {
  const std::string header = "time_s,event,joint";
  const fs::path ours = scratch("ours.csv");
  EXPECT_EQ(refusal([&] { checkAppendFile(ours.string(), {header}, "~journal_file", false); }), "")
      << "a missing file is fine";
  std::ofstream(ours) << header << "\n1,move,height\n";
  EXPECT_EQ(refusal([&] { checkAppendFile(ours.string(), {header}, "~journal_file", false); }), "");
  const fs::path theirs = scratch("theirs.csv");
  std::ofstream(theirs) << "name,salary\n";
  const std::string why =
      refusal([&] { checkAppendFile(theirs.string(), {header}, "~journal_file", false); });
  EXPECT_NE(why.find("~journal_file"), std::string::npos) << why;
  EXPECT_NE(why.find("name,salary"), std::string::npos) << why;
  EXPECT_NE(refusal([] { checkAppendFile("/etc/hosts", {"x"}, "~journal_file", false); }), "");
  EXPECT_NE(refusal([] { checkAppendFile("/tmp", {"x"}, "~journal_file", false); }), "")
      << "a folder is not a journal";
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
