// A ROS-2-shaped peer on eProsima Fast DDS (Debian's libfastrtps-dev, types from fastddsgen), built by
// the interop tests. Topics only (Fast DDS's services carry the request identity in inline QoS).
//
//   fastdds_peer listen NS SECONDS          print joint_states, robot_description, tf_static
//   fastdds_peer traj NS T joint=pos ...    publish one trajectory_msgs/JointTrajectory point at T s
//
// The participant takes its transports from the default XML profile (FASTRTPS_DEFAULT_PROFILES_FILE):
// the tests give it an interface whitelist of 127.0.0.1 and a loopback initial peer.
#include <chrono>
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

int main(int argc, char **argv) {
  if (argc < 4) { std::fprintf(stderr, "usage: see the source\n"); return 2; }
  const char *dom = std::getenv("ROS_DOMAIN_ID");
  pp = DomainParticipantFactory::get_instance()->create_participant(dom && *dom ? std::atoi(dom) : 0, PARTICIPANT_QOS_DEFAULT);
  if (!pp) { std::fprintf(stderr, "participant failed\n"); return 2; }
  int rc = 2;
  if (!std::strcmp(argv[1], "listen")) rc = listen(argv[2], std::atof(argv[3]));
  else if (!std::strcmp(argv[1], "traj")) rc = traj(argv[2], std::atof(argv[3]), argc - 4, argv + 4);
  std::fflush(stdout);
  pp->delete_contained_entities();
  DomainParticipantFactory::get_instance()->delete_participant(pp);
  return rc;
}
