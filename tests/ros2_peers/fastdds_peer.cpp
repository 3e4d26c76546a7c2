// A ROS-2-shaped peer on eProsima Fast DDS (Debian's libfastrtps-dev, types from fastddsgen), built by
// the interop tests. Topics only (Fast DDS's services carry the request identity in inline QoS).
//
//   fastdds_peer listen NS SECONDS          print joint_states, robot_description, tf_static
//   fastdds_peer traj NS T joint=pos ...    publish one trajectory_msgs/JointTrajectory point at T s
//   fastdds_peer jtc NS SECONDS joint=pos ... play a ros2_control JointTrajectoryController for SECONDS:
//       joint_states out (reliable, 100 Hz, wall-clock stamps), joint_trajectory_controller/joint_trajectory
//       in (each trajectory replaces the current one from the current position, interpolated linearly
//       through its points; an empty one holds). SIGUSR1 stops joint_states (prints STOPPED); the
//       controller keeps running. Prints HOLD for each empty trajectory, then TRAJ and FINAL.
//
// The participant takes its transports from the default XML profile (FASTRTPS_DEFAULT_PROFILES_FILE):
// the tests give it an interface whitelist of 127.0.0.1 and a loopback initial peer.
#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>

#include "ros_typesPubSubTypes.h"

using namespace eprosima::fastdds::dds;
using Clock = std::chrono::steady_clock;

static DomainParticipant *pp;

static std::string ros_topic(const std::string &ns, const std::string &name) {
  std::string n = ns;
  while (!n.empty() && n[0] == '/') n.erase(0, 1);
  return "rt/" + (n.empty() ? "" : n + "/") + name;
}

static Topic *topic(TopicDataType *type, const std::string &name) {
  TypeSupport ts(type);
  ts.register_type(pp);
  Topic *t = pp->create_topic(name, ts.get_type_name(), TOPIC_QOS_DEFAULT);
  if (!t) { std::fprintf(stderr, "topic %s failed\n", name.c_str()); std::exit(2); }
  return t;
}

static DataReader *reader(Subscriber *sub, Topic *t, bool transient, int depth) {
  DataReaderQos q = DATAREADER_QOS_DEFAULT;
  q.reliability().kind = RELIABLE_RELIABILITY_QOS;
  q.durability().kind = transient ? TRANSIENT_LOCAL_DURABILITY_QOS : VOLATILE_DURABILITY_QOS;
  q.history().kind = KEEP_LAST_HISTORY_QOS;
  q.history().depth = depth;
  return sub->create_datareader(t, q);
}

static int listen(const std::string &ns, double seconds) {
  Subscriber *sub = pp->create_subscriber(SUBSCRIBER_QOS_DEFAULT);
  DataReader *js = reader(sub, topic(new sensor_msgs::msg::dds_::JointState_PubSubType(), ros_topic(ns, "joint_states")), false, 100);
  DataReader *desc = reader(sub, topic(new std_msgs::msg::dds_::String_PubSubType(), ros_topic(ns, "robot_description")), true, 1);
  DataReader *tfs = reader(sub, topic(new tf2_msgs::msg::dds_::TFMessage_PubSubType(), ros_topic(ns, "tf_static")), true, 1);
  auto end = Clock::now() + std::chrono::duration<double>(seconds);
  SampleInfo info;
  while (Clock::now() < end) {
    sensor_msgs::msg::dds_::JointState_ m;
    while (js->take_next_sample(&m, &info) == ReturnCode_t::RETCODE_OK) {
      if (!info.valid_data) continue;
      std::printf("JS %d %u %zu", m.header().stamp().sec(), m.header().stamp().nanosec(), m.name().size());
      for (size_t k = 0; k < m.name().size(); k++) std::printf(" %s %.17g", m.name()[k].c_str(), m.position()[k]);
      std::printf("\n");
    }
    std_msgs::msg::dds_::String_ s;
    if (desc->take_next_sample(&s, &info) == ReturnCode_t::RETCODE_OK && info.valid_data)
      std::printf("DESC %zu %.40s\n", s.data().size(), s.data().c_str());
    tf2_msgs::msg::dds_::TFMessage_ tf;
    if (tfs->take_next_sample(&tf, &info) == ReturnCode_t::RETCODE_OK && info.valid_data) {
      std::printf("TFS %zu", tf.transforms().size());
      for (auto &t : tf.transforms()) std::printf(" %s>%s", t.header().frame_id().c_str(), t.child_frame_id().c_str());
      std::printf("\n");
    }
    std::fflush(stdout);
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  return 0;
}

static int traj(const std::string &ns, double t, int argc, char **argv) {
  Publisher *pub = pp->create_publisher(PUBLISHER_QOS_DEFAULT);
  DataWriterQos q = DATAWRITER_QOS_DEFAULT;
  q.reliability().kind = RELIABLE_RELIABILITY_QOS;
  q.durability().kind = VOLATILE_DURABILITY_QOS;
  q.history().kind = KEEP_LAST_HISTORY_QOS;
  q.history().depth = 10;
  DataWriter *w = pub->create_datawriter(
      topic(new trajectory_msgs::msg::dds_::JointTrajectory_PubSubType(), ros_topic(ns, "joint_trajectory_controller/joint_trajectory")), q);
  auto end = Clock::now() + std::chrono::seconds(20);
  PublicationMatchedStatus st;
  for (;;) {
    w->get_publication_matched_status(st);
    if (st.current_count > 0) break;
    if (Clock::now() > end) { std::printf("NOMATCH\n"); return 1; }
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  trajectory_msgs::msg::dds_::JointTrajectory_ m;
  trajectory_msgs::msg::dds_::JointTrajectoryPoint_ pt;
  for (int i = 0; i < argc; i++) {
    std::string a = argv[i];
    size_t eq = a.find('=');
    if (eq == std::string::npos) { std::fprintf(stderr, "expected joint=pos\n"); return 2; }
    m.joint_names().push_back(a.substr(0, eq));
    pt.positions().push_back(std::strtod(a.c_str() + eq + 1, nullptr));
  }
  pt.time_from_start().sec(static_cast<int32_t>(t));
  pt.time_from_start().nanosec(static_cast<uint32_t>((t - static_cast<int32_t>(t)) * 1e9));
  m.points().push_back(pt);
  bool ok = w->write(&m);
  std::printf("SENT %d\n", ok ? 0 : -1);
  std::fflush(stdout);
  std::this_thread::sleep_for(std::chrono::seconds(1));
  return ok ? 0 : 1;
}

static volatile std::sig_atomic_t stop_states = 0;
static void on_usr1(int) { stop_states = 1; }

struct Plan {
  double t0 = 0;
  std::vector<double> start;
  std::vector<double> times;
  std::vector<std::vector<double>> pos;
};

// positions and velocities of the plan at time t (linear between the points, then the last point)
static void eval(const Plan &p, double t, std::vector<double> &q, std::vector<double> &v) {
  double dt = t - p.t0, prev_t = 0;
  const std::vector<double> *prev = &p.start;
  q = p.start;
  v.assign(q.size(), 0.0);
  for (size_t k = 0; k < p.times.size(); k++) {
    const std::vector<double> &nxt = p.pos[k];
    double span = p.times[k] - prev_t;
    if (dt <= p.times[k]) {
      double a = span > 0 ? (dt - prev_t) / span : 1.0;
      for (size_t j = 0; j < q.size(); j++) {
        q[j] = (*prev)[j] + a * (nxt[j] - (*prev)[j]);
        v[j] = span > 0 ? (nxt[j] - (*prev)[j]) / span : 0.0;
      }
      return;
    }
    prev_t = p.times[k];
    prev = &nxt;
  }
  q = *prev;
}

static int jtc(const std::string &ns, double seconds, int argc, char **argv) {
  std::vector<std::string> names;
  Plan plan;
  for (int i = 0; i < argc; i++) {
    std::string a = argv[i];
    size_t eq = a.find('=');
    if (eq == std::string::npos) { std::fprintf(stderr, "expected joint=pos\n"); return 2; }
    names.push_back(a.substr(0, eq));
    plan.start.push_back(std::strtod(a.c_str() + eq + 1, nullptr));
  }
  std::signal(SIGUSR1, on_usr1);
  Publisher *pub = pp->create_publisher(PUBLISHER_QOS_DEFAULT);
  DataWriterQos wq = DATAWRITER_QOS_DEFAULT;
  wq.reliability().kind = RELIABLE_RELIABILITY_QOS;
  wq.durability().kind = VOLATILE_DURABILITY_QOS;
  wq.history().kind = KEEP_LAST_HISTORY_QOS;
  wq.history().depth = 10;
  DataWriter *js = pub->create_datawriter(
      topic(new sensor_msgs::msg::dds_::JointState_PubSubType(), ros_topic(ns, "joint_states")), wq);
  Subscriber *sub = pp->create_subscriber(SUBSCRIBER_QOS_DEFAULT);
  DataReader *tr = reader(sub, topic(new trajectory_msgs::msg::dds_::JointTrajectory_PubSubType(),
                                     ros_topic(ns, "joint_trajectory_controller/joint_trajectory")), false, 100);
  auto t_start = Clock::now();
  auto now = [&] { return std::chrono::duration<double>(Clock::now() - t_start).count(); };
  std::vector<double> q, v;
  long received = 0, holds = 0, rejected = 0;
  double next_pub = 0;
  bool stopped = false;
  SampleInfo info;
  while (now() < seconds) {
    trajectory_msgs::msg::dds_::JointTrajectory_ m;
    while (tr->take_next_sample(&m, &info) == ReturnCode_t::RETCODE_OK) {
      if (!info.valid_data) continue;
      double t = now();
      eval(plan, t, q, v);
      std::vector<int> idx;
      bool ok = true;
      for (auto &n : m.joint_names()) {
        int found = -1;
        for (size_t j = 0; j < names.size(); j++) if (names[j] == n) found = static_cast<int>(j);
        if (found < 0) ok = false;
        idx.push_back(found);
      }
      for (auto &p : m.points()) if (p.positions().size() != idx.size()) ok = false;
      if (!ok) { rejected++; std::printf("REJECT %.3f\n", t); std::fflush(stdout); continue; }
      Plan next;
      next.t0 = t;
      next.start = q;
      for (auto &p : m.points()) {
        std::vector<double> target = q;
        for (size_t k = 0; k < idx.size(); k++) target[idx[k]] = p.positions()[k];
        next.times.push_back(p.time_from_start().sec() + p.time_from_start().nanosec() * 1e-9);
        next.pos.push_back(target);
      }
      plan = next;
      if (m.points().empty()) { holds++; std::printf("HOLD %.3f\n", t); std::fflush(stdout); }
      else received++;
    }
    double t = now();
    if (stop_states && !stopped) { stopped = true; std::printf("STOPPED %.3f\n", t); std::fflush(stdout); }
    if (!stopped && t >= next_pub) {
      eval(plan, t, q, v);
      sensor_msgs::msg::dds_::JointState_ s;
      auto wall = std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
      s.header().stamp().sec(static_cast<int32_t>(wall));
      s.header().stamp().nanosec(static_cast<uint32_t>((wall - static_cast<int32_t>(wall)) * 1e9));
      s.name(names);
      s.position(q);
      s.velocity(v);
      js->write(&s);
      next_pub = t + 0.01;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  eval(plan, now(), q, v);
  std::printf("TRAJ %ld %ld %ld\nFINAL", received, holds, rejected);
  for (size_t j = 0; j < names.size(); j++) std::printf(" %s=%.9f", names[j].c_str(), q[j]);
  std::printf("\n");
  return 0;
}

int main(int argc, char **argv) {
  if (argc < 4) { std::fprintf(stderr, "usage: see the source\n"); return 2; }
  const char *dom = std::getenv("ROS_DOMAIN_ID");
  pp = DomainParticipantFactory::get_instance()->create_participant(dom && *dom ? std::atoi(dom) : 0, PARTICIPANT_QOS_DEFAULT);
  if (!pp) { std::fprintf(stderr, "participant failed\n"); return 2; }
  int rc = 2;
  if (!std::strcmp(argv[1], "listen")) rc = listen(argv[2], std::atof(argv[3]));
  else if (!std::strcmp(argv[1], "traj")) rc = traj(argv[2], std::atof(argv[3]), argc - 4, argv + 4);
  else if (!std::strcmp(argv[1], "jtc")) rc = jtc(argv[2], std::atof(argv[3]), argc - 4, argv + 4);
  std::fflush(stdout);
  pp->delete_contained_entities();
  DomainParticipantFactory::get_instance()->delete_participant(pp);
  return rc;
}
