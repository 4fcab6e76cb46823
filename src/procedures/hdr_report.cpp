#include "needle_guidance/procedures/hdr_report.h"

#include "needle_guidance/delivery/journal.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <sstream>

#include "needle_guidance/report/plot.h"
#include "needle_guidance/report/table.h"

namespace needle_guidance {
namespace procedures {
namespace {

std::string jsonNumber(double v) {
  return report::jsonNumber(v, 8);
}

std::string jsonText(const std::string& s) {
  std::string out;
  for (char ch : s) {
    if (ch == '"' || ch == '\\')
      out += '\\';
    out += ch == '\n' ? ' ' : ch;
  }
  return "\"" + out + "\"";
}

double indexValue(const std::vector<DeliveryEvaluation::Index>& indices, const std::string& name,
                  double DeliveryEvaluation::Index::*field) {
  for (const auto& index : indices) {
    if (index.name == name)
      return index.*field;
  }
  return std::nan("");
}

void writeDvhPlot(const HdrDeliveryReport& r, const std::string& path) {
  report::LinePlot plot("Planned DVH, plan " + r.plan_id, "dose [Gy]", "volume [%]");
  std::size_t k = 0;
  for (const auto& [name, volume] : r.dvh)
    plot.addLine(name, r.dvh_dose_Gy, volume, report::seriesColour(k++));
  plot.setYRange(0.0, 105.0);
  plot.save(path);
}

void writeDwellPlot(const HdrDeliveryReport& r, const std::string& path) {
  report::LinePlot plot("Dwell times, planned and delivered (" + r.delivered_from + ")",
                        "dwell (schedule order)", "time [s]");
  std::vector<double> k, planned, delivered;
  for (std::size_t i = 0; i < r.dwells.size(); ++i) {
    k.push_back(static_cast<double>(i));
    planned.push_back(r.dwells[i].planned_s);
    delivered.push_back(r.dwells[i].delivered_s);
  }
  plot.addPoints("planned", k, planned, report::seriesColour(0), 5);
  plot.addPoints("delivered", k, delivered, report::seriesColour(1), 3);
  plot.save(path);
}

}  // namespace

double HdrDeliveryReport::plannedTotal_s() const {
  double s = 0.0;
  for (const auto& d : dwells)
    s += d.planned_s;
  return s;
}

double HdrDeliveryReport::deliveredTotal_s() const {
  double s = 0.0;
  for (const auto& d : dwells)
    s += d.delivered_s;
  return s;
}

double HdrDeliveryReport::maxDwellError_s() const {
  double e = 0.0;
  for (const auto& d : dwells)
    e = std::max(e, std::abs(d.delivered_s - d.planned_s));
  return e;
}

bool HdrDeliveryReport::success() const {
  return dead_node.empty() && status == "completed" && !dwells.empty() &&
         maxDwellError_s() <= tolerance_s && !indices.empty();
}

void HdrDeliveryReport::deliveredFromJournal(const delivery::Schedule& schedule,
                                             const std::string& journal_path) {
  journal = journal_path;
  delivered_from = "journal";
  dwells.clear();
  try {
    if (!std::filesystem::is_regular_file(journal_path)) {  // opening would create it
      throw std::runtime_error("no journal file at '" + journal_path + "'");
    }
    const delivery::Journal records(journal_path);
    const delivery::Ledger ledger = delivery::replay(records.records(), &schedule, 0.5);
    for (const auto& c : schedule.channels) {
      for (std::size_t k = 0; k < c.time_s.size(); ++k) {
        const auto key = std::make_pair(c.channel, c.dwell_index[k]);
        const auto d = ledger.delivered_s.find(key);
        const auto u = ledger.uncertainty_s.find(key);
        dwells.push_back({c.channel, c.dwell_index[k], c.time_s[k],
                          d == ledger.delivered_s.end() ? 0.0 : d->second,
                          u == ledger.uncertainty_s.end() ? 0.0 : u->second});
      }
    }
    message = std::to_string(records.records().size()) + " journal records";
  } catch (const std::exception& e) {
    delivered_from = std::string("nothing: journal not readable: ") + e.what();
    for (const auto& c : schedule.channels) {
      for (std::size_t k = 0; k < c.time_s.size(); ++k)
        dwells.push_back({c.channel, c.dwell_index[k], c.time_s[k], 0.0, 0.0});
    }
  }
}

void HdrDeliveryReport::write(const std::string& dir) const {
  report::Table table(
      {"channel", "dwell_index", "planned_s", "delivered_s", "error_s", "uncertainty_s"});
  for (const auto& d : dwells) {
    table.addRow({double(d.channel), double(d.dwell_index), d.planned_s, d.delivered_s,
                  d.delivered_s - d.planned_s, d.uncertainty_s});
  }
  report::Table index_table({"index", "planned", "delivered", "delivered_with_transit"});
  for (const auto& i : indices)
    index_table.addRow({i.name, i.planned, i.delivered, i.with_transit});

  std::ostringstream json;
  json << "{\n  \"procedure\": \"hdr_delivery\",\n  \"scene\": " << jsonText(case_name)
       << ",\n  \"success\": " << (success() ? "true" : "false")
       << ",\n  \"status\": " << jsonText(status) << ",\n  \"plan_id\": " << jsonText(plan_id)
       << ",\n  \"method\": " << jsonText(method) << ",\n  \"objective\": " << jsonNumber(objective)
       << ",\n  \"planned_dwell_s\": " << jsonNumber(plannedTotal_s())
       << ",\n  \"delivered_dwell_s\": " << jsonNumber(deliveredTotal_s())
       << ",\n  \"delivered_from\": " << jsonText(delivered_from)
       << ",\n  \"max_dwell_error_s\": " << jsonNumber(maxDwellError_s())
       << ",\n  \"interruptions\": " << interruptions
       << ",\n  \"transit_in_patient_s\": " << jsonNumber(transit_in_patient_s)
       << ",\n  \"prostate_V100_delivered_pct\": "
       << jsonNumber(indexValue(indices, "prostate_V100", &DeliveryEvaluation::Index::delivered))
       << ",\n  \"prostate_D90_with_transit_Gy\": "
       << jsonNumber(indexValue(indices, "prostate_D90", &DeliveryEvaluation::Index::with_transit))
       << ",\n  \"transit_dose_max_Gy\": " << jsonNumber(transit_dose_max_Gy);
  if (!cause.empty()) {
    json << ",\n  \"dead_node\": " << jsonText(dead_node) << ",\n  \"cause\": " << jsonText(cause)
         << ",\n  \"detect_s\": " << jsonNumber(detect_s);
  }
  if (detected_unix_s > 0.0)  // a death was seen (the cause, or a restart that was resumed)
    json << ",\n  \"detected_unix_s\": " << report::jsonNumber(detected_unix_s, 15);
  json << ",\n  \"afterloader_restarts\": " << afterloader_restarts;
  json << ",\n  \"wall_s\": " << jsonNumber(wall_s) << "\n}\n";

  std::ostringstream md;
  md << "# HDR delivery — case `" << case_name << "`, plan `" << plan_id << "`"
     << (cause.empty() ? "" : ": STOPPED") << "\n\n"
     << "Plan (" << method << ", dissertation ch. 6): objective " << objective << ", "
     << plannedTotal_s() << " s of dwell time in " << channels << " channels, source S_K "
     << source_U << " U (" << decay_days << " days after calibration).\n\n";
  if (!cause.empty()) {
    md << "**" << cause << ".** The delivery was stopped; what was delivered comes from the "
       << delivered_from << " (`" << journal << "`): " << deliveredTotal_s() << " s of "
       << plannedTotal_s() << " s planned. On a restart the afterloader recovers from this "
       << "journal with the source in its safe and resumes when the same schedule is sent "
       << "again (respawn:=true does this automatically).\n\n";
  } else {
    md << "Delivery: " << status << " — " << message << "; " << interruptions
       << " interruption(s); source transit inside the patient " << transit_in_patient_s
       << " s (its dose is in the last column of the indices). Journal: `" << journal << "`.\n\n";
  }
  if (!indices.empty()) {
    md << "## Dose indices (V in % of volume, D in Gy)\n\n"
       << index_table.toMarkdown()
       << "\nLargest transit dose at a dose point: " << transit_dose_max_Gy << " Gy.\n\n";
  }
  if (!dvh.empty())
    md << "Planned DVH: `dvh.png`. ";
  md << "Dwell times planned and delivered: `dwells.png`.\n\n## Planned vs delivered per dwell\n\n"
     << table.toMarkdown() << "\nResult: " << (success() ? "PASS" : "FAIL")
     << ", largest dwell-time error " << maxDwellError_s() << " s (tolerance " << tolerance_s
     << " s), wall time " << wall_s << " s.\n";

  table.writeCsv(dir + "/delivery.csv");
  if (!indices.empty())
    index_table.writeCsv(dir + "/indices.csv");
  if (!dvh.empty())
    writeDvhPlot(*this, dir + "/dvh.png");
  if (!dwells.empty())
    writeDwellPlot(*this, dir + "/dwells.png");
  report::writeTextFile(dir + "/summary.md", md.str());
  report::writeTextFile(dir + "/summary.json", json.str());
}

std::string HdrDeliveryReport::consoleSummary(const std::string& dir) const {
  std::ostringstream out;
  out << "\n== HDR delivery of case '" << case_name << "' ==\n";
  if (!indices.empty()) {
    report::Table index_table({"index", "planned", "delivered", "delivered_with_transit"});
    for (const auto& i : indices)
      index_table.addRow({i.name, i.planned, i.delivered, i.with_transit});
    out << index_table.toText();
  }
  out << (success() ? "PASS" : "FAIL") << ": " << (cause.empty() ? status : cause) << ", "
      << dwells.size() << " dwells, delivered " << deliveredTotal_s() << " s of "
      << plannedTotal_s() << " s planned (from the " << delivered_from << "), max dwell error "
      << maxDwellError_s() << " s, " << interruptions << " interruption(s), transit "
      << transit_in_patient_s << " s, " << wall_s << " s; report in " << dir << "\n";
  return out.str();
}

}  // namespace procedures
}  // namespace needle_guidance
