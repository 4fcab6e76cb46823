#include <gtest/gtest.h>

#include "needle_guidance/report/table.h"

namespace needle_guidance::report {
namespace {

TEST(TableTest, FormatsCsvMarkdownAndText) {
  Table table({"name", "error_mm"}, 3);
  table.addRow({std::string("t01"), 0.12345});
  table.addRow({std::string("a,b"), 2.0});
  EXPECT_EQ(table.toCsv(), "name,error_mm\nt01,0.123\n\"a,b\",2\n");
  EXPECT_EQ(table.toMarkdown(),
            "| name | error_mm |\n| --- | --- |\n| t01 | 0.123 |\n| a,b | 2 |\n");
  EXPECT_EQ(table.toText(), "name  error_mm\n t01     0.123\n a,b         2\n");
  EXPECT_DOUBLE_EQ(table.number(0, "error_mm"), 0.12345);
  EXPECT_THROW(table.number(0, "name"), std::invalid_argument);
  EXPECT_THROW(table.addRow({1.0}), std::invalid_argument);
  EXPECT_THROW(Table({}), std::invalid_argument);
}

}  // namespace
}  // namespace needle_guidance::report

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
