/* A ROS-2-shaped peer on Eclipse Cyclone DDS C (Debian's cyclonedds-dev), built by the interop tests.
 *
 *   cyclone_peer listen NS SECONDS           print joint_states, robot_description, tf_static
 *   cyclone_peer traj NS T joint=pos ...     publish one trajectory_msgs/JointTrajectory point at T s
 *   cyclone_peer action NS T CANCEL_AFTER joint=pos ...
 *        FollowJointTrajectory client in rmw_cyclonedds' request format (request header = the
 *        request writer's instance handle + sequence number); cancels after CANCEL_AFTER feedback
 *        messages when CANCEL_AFTER > 0.
 *   cyclone_peer trigger NS SERVICE          call a std_srvs/Trigger service (estop, reset, enable)
 * Topic names follow ROS 2's mapping (rt/, rq/...Request, rr/...Reply). Output: one line per event.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>
#include "dds/dds.h"
#include "ros_types.h"

static dds_entity_t pp;

static dds_qos_t *qos(int reliable, int transient, int depth) {
  dds_qos_t *q = dds_create_qos();
  if (reliable) dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_SECS(1));
  else dds_qset_reliability(q, DDS_RELIABILITY_BEST_EFFORT, 0);
  dds_qset_durability(q, transient ? DDS_DURABILITY_TRANSIENT_LOCAL : DDS_DURABILITY_VOLATILE);
  dds_qset_history(q, DDS_HISTORY_KEEP_LAST, depth);
  return q;
}

static dds_entity_t topic(const dds_topic_descriptor_t *d, const char *prefix, const char *ns, const char *name,
                          const char *suffix) {
  char buf[512];
  snprintf(buf, sizeof buf, "%s%s%s%s%s", prefix, ns[0] == '/' ? ns + 1 : ns, ns[0] && strcmp(ns, "/") ? "/" : "",
           name, suffix);
  dds_entity_t t = dds_create_topic(pp, d, buf, NULL, NULL);
  if (t < 0) { fprintf(stderr, "topic %s: %s\n", buf, dds_strretcode(t)); exit(2); }
  return t;
}

static dds_entity_t reader(dds_entity_t t, dds_qos_t *q) {
  dds_entity_t r = dds_create_reader(pp, t, q, NULL);
  dds_delete_qos(q);
  if (r < 0) { fprintf(stderr, "reader: %s\n", dds_strretcode(r)); exit(2); }
  return r;
}

static dds_entity_t writer(dds_entity_t t, dds_qos_t *q) {
  dds_entity_t w = dds_create_writer(pp, t, q, NULL);
  dds_delete_qos(q);
  if (w < 0) { fprintf(stderr, "writer: %s\n", dds_strretcode(w)); exit(2); }
  return w;
}

static int wait_matched_pub(dds_entity_t w, double seconds) {
  dds_time_t end = dds_time() + (dds_duration_t)(seconds * 1e9);
  dds_publication_matched_status_t st;
  while (dds_time() < end) {
    dds_get_publication_matched_status(w, &st);
    if (st.current_count > 0) return 1;
    dds_sleepfor(DDS_MSECS(5));
  }
  return 0;
}

static int wait_matched_sub(dds_entity_t r, double seconds) {
  dds_time_t end = dds_time() + (dds_duration_t)(seconds * 1e9);
  dds_subscription_matched_status_t st;
  while (dds_time() < end) {
    dds_get_subscription_matched_status(r, &st);
    if (st.current_count > 0) return 1;
    dds_sleepfor(DDS_MSECS(5));
  }
  return 0;
}

static int listen(const char *ns, double seconds) {
  dds_entity_t js = reader(topic(&sensor_msgs_msg_dds__JointState__desc, "rt/", ns, "joint_states", ""), qos(1, 0, 100));
  dds_entity_t desc = reader(topic(&std_msgs_msg_dds__String__desc, "rt/", ns, "robot_description", ""), qos(1, 1, 1));
  dds_entity_t tfs = reader(topic(&tf2_msgs_msg_dds__TFMessage__desc, "rt/", ns, "tf_static", ""), qos(1, 1, 1));
  dds_time_t end = dds_time() + (dds_duration_t)(seconds * 1e9);
  void *s[64];
  dds_sample_info_t info[64];
  while (dds_time() < end) {
    int n;
    memset(s, 0, sizeof s);
    n = dds_take(js, s, info, 64, 64);
    for (int i = 0; i < n; i++) {
      if (!info[i].valid_data) continue;
      sensor_msgs_msg_dds__JointState_ *m = s[i];
      printf("JS %d %u %u", m->header.stamp.sec, m->header.stamp.nanosec, m->name._length);
      for (uint32_t k = 0; k < m->name._length; k++) printf(" %s %.17g", m->name._buffer[k], m->position._buffer[k]);
      printf("\n");
    }
    if (n > 0) dds_return_loan(js, s, n);
    memset(s, 0, sizeof s);
    n = dds_take(desc, s, info, 1, 1);
    if (n > 0 && info[0].valid_data) {
      std_msgs_msg_dds__String_ *m = s[0];
      printf("DESC %zu %.40s\n", strlen(m->data), m->data);
    }
    if (n > 0) dds_return_loan(desc, s, n);
    memset(s, 0, sizeof s);
    n = dds_take(tfs, s, info, 1, 1);
    if (n > 0 && info[0].valid_data) {
      tf2_msgs_msg_dds__TFMessage_ *m = s[0];
      printf("TFS %u", m->transforms._length);
      for (uint32_t k = 0; k < m->transforms._length; k++)
        printf(" %s>%s", m->transforms._buffer[k].header.frame_id, m->transforms._buffer[k].child_frame_id);
      printf("\n");
    }
    if (n > 0) dds_return_loan(tfs, s, n);
    fflush(stdout);
    dds_sleepfor(DDS_MSECS(2));
  }
  return 0;
}

/* joint=pos arguments into names/positions (pos may be "nan") */
static uint32_t parse_points(int argc, char **argv, char ***names, double **pos) {
  *names = calloc((size_t)argc, sizeof(char *));
  *pos = calloc((size_t)argc, sizeof(double));
  for (int i = 0; i < argc; i++) {
    char *eq = strchr(argv[i], '=');
    if (!eq) { fprintf(stderr, "expected joint=pos, got %s\n", argv[i]); exit(2); }
    *eq = 0;
    (*names)[i] = argv[i];
    (*pos)[i] = strtod(eq + 1, NULL);
  }
  return (uint32_t)argc;
}

static void fill_trajectory(trajectory_msgs_msg_dds__JointTrajectory_ *m,
                            trajectory_msgs_msg_dds__JointTrajectoryPoint_ *pt, double t, uint32_t n, char **names,
                            double *pos) {
  memset(m, 0, sizeof *m);
  memset(pt, 0, sizeof *pt);
  m->header.frame_id = "";
  m->joint_names._length = m->joint_names._maximum = n;
  m->joint_names._buffer = names;
  pt->positions._length = pt->positions._maximum = n;
  pt->positions._buffer = pos;
  pt->time_from_start.sec = (int32_t)floor(t);
  pt->time_from_start.nanosec = (uint32_t)((t - floor(t)) * 1e9);
  m->points._length = m->points._maximum = 1;
  m->points._buffer = pt;
}

static int traj(const char *ns, double t, int argc, char **argv) {
  char **names; double *pos;
  uint32_t n = parse_points(argc, argv, &names, &pos);
  dds_entity_t w = writer(topic(&trajectory_msgs_msg_dds__JointTrajectory__desc, "rt/", ns,
                                "joint_trajectory_controller/joint_trajectory", ""), qos(1, 0, 10));
  if (!wait_matched_pub(w, 20.0)) { printf("NOMATCH\n"); return 1; }
  dds_sleepfor(DDS_MSECS(200));
  trajectory_msgs_msg_dds__JointTrajectory_ m;
  trajectory_msgs_msg_dds__JointTrajectoryPoint_ pt;
  fill_trajectory(&m, &pt, t, n, names, pos);
  dds_return_t rc = dds_write(w, &m);
  printf("SENT %d\n", rc);
  fflush(stdout);
  dds_sleepfor(DDS_SECS(1));
  return rc < 0;
}

typedef struct { dds_entity_t req, rep; uint64_t guid; int64_t seq; } client_t;

static void client(client_t *c, const char *ns, const char *name, const dds_topic_descriptor_t *rq,
                   const dds_topic_descriptor_t *rr) {
  char full[256];
  snprintf(full, sizeof full, "joint_trajectory_controller/follow_joint_trajectory/_action/%s", name);
  c->req = writer(topic(rq, "rq/", ns, full, "Request"), qos(1, 0, 100));
  c->rep = reader(topic(rr, "rr/", ns, full, "Reply"), qos(1, 0, 100));
  dds_instance_handle_t ih;
  dds_get_instance_handle(c->req, &ih);
  c->guid = ih; /* rmw_cyclonedds: the request writer's instance handle identifies the client */
  c->seq = 0;
}

/* take one reply addressed to this client (guid and seq), or NULL */
static void *take_reply(client_t *c, int64_t seq, void **loan) {
  dds_sample_info_t info;
  void *s[1] = {NULL};
  while (dds_take(c->rep, s, &info, 1, 1) == 1) {
    agentsdk_ros2_RequestHeader *h = s[0]; /* every reply type starts with the header */
    if (info.valid_data && h->guid == c->guid && h->seq == seq) { *loan = s[0]; return s[0]; }
    dds_return_loan(c->rep, s, 1);
    s[0] = NULL;
  }
  return NULL;
}

static int action(const char *ns, double t, int cancel_after, int argc, char **argv) {
  char **names; double *pos;
  uint32_t n = parse_points(argc, argv, &names, &pos);
  client_t send, result, cancel;
  client(&send, ns, "send_goal", &control_msgs_action_dds__FollowJointTrajectory_SendGoal_Request__desc,
         &control_msgs_action_dds__FollowJointTrajectory_SendGoal_Response__desc);
  client(&result, ns, "get_result", &control_msgs_action_dds__FollowJointTrajectory_GetResult_Request__desc,
         &control_msgs_action_dds__FollowJointTrajectory_GetResult_Response__desc);
  client(&cancel, ns, "cancel_goal", &action_msgs_srv_dds__CancelGoal_Request__desc,
         &action_msgs_srv_dds__CancelGoal_Response__desc);
  dds_entity_t fb = reader(topic(&control_msgs_action_dds__FollowJointTrajectory_FeedbackMessage__desc, "rt/", ns,
                                 "joint_trajectory_controller/follow_joint_trajectory/_action/feedback", ""),
                           qos(1, 0, 100));
  dds_entity_t status = reader(topic(&action_msgs_msg_dds__GoalStatusArray__desc, "rt/", ns,
                                     "joint_trajectory_controller/follow_joint_trajectory/_action/status", ""),
                               qos(1, 1, 1));
  client_t *all[3] = {&send, &result, &cancel};
  for (int i = 0; i < 3; i++)
    if (!wait_matched_pub(all[i]->req, 20.0) || !wait_matched_sub(all[i]->rep, 20.0)) { printf("NOMATCH\n"); return 1; }
  wait_matched_sub(fb, 5.0);
  dds_sleepfor(DDS_MSECS(200));

  control_msgs_action_dds__FollowJointTrajectory_SendGoal_Request_ g;
  trajectory_msgs_msg_dds__JointTrajectoryPoint_ pt;
  memset(&g, 0, sizeof g);
  fill_trajectory(&g.goal.trajectory, &pt, t, n, names, pos);
  g.goal.multi_dof_trajectory.header.frame_id = "";
  for (int i = 0; i < 16; i++) g.goal_id.uuid[i] = (uint8_t)(rand() & 0xff);
  g.request_header.guid = send.guid;
  g.request_header.seq = ++send.seq;
  dds_write(send.req, &g);
  void *loan = NULL, *rep = NULL;
  dds_time_t end = dds_time() + DDS_SECS(30);
  while (!(rep = take_reply(&send, send.seq, &loan)) && dds_time() < end) dds_sleepfor(DDS_MSECS(2));
  if (!rep) { printf("NOREPLY\n"); return 1; }
  int accepted = ((control_msgs_action_dds__FollowJointTrajectory_SendGoal_Response_ *)rep)->accepted;
  printf("ACCEPTED %d\n", accepted);
  fflush(stdout);
  dds_return_loan(send.rep, &loan, 1);
  if (!accepted) return 0;

  control_msgs_action_dds__FollowJointTrajectory_GetResult_Request_ r;
  memset(&r, 0, sizeof r);
  memcpy(r.goal_id.uuid, g.goal_id.uuid, 16);
  r.request_header.guid = result.guid;
  r.request_header.seq = ++result.seq;
  dds_write(result.req, &r);

  int feedbacks = 0, canceled = 0, last_status = -1;
  end = dds_time() + DDS_SECS(60);
  while (dds_time() < end) {
    void *s[16];
    dds_sample_info_t info[16];
    memset(s, 0, sizeof s);
    int k = dds_take(fb, s, info, 16, 16);
    for (int i = 0; i < k; i++) {
      control_msgs_action_dds__FollowJointTrajectory_FeedbackMessage_ *m = s[i];
      if (!info[i].valid_data || memcmp(m->goal_id.uuid, g.goal_id.uuid, 16) != 0) continue;
      feedbacks++;
      printf("FEEDBACK %d %d %u", feedbacks, m->feedback.header.stamp.sec, m->feedback.header.stamp.nanosec);
      for (uint32_t j = 0; j < m->feedback.actual.positions._length; j++)
        printf(" %s %.17g", m->feedback.joint_names._buffer[j], m->feedback.actual.positions._buffer[j]);
      printf("\n");
    }
    if (k > 0) dds_return_loan(fb, s, k);
    memset(s, 0, sizeof s);
    k = dds_take(status, s, info, 1, 1);
    if (k > 0 && info[0].valid_data) {
      action_msgs_msg_dds__GoalStatusArray_ *m = s[0];
      for (uint32_t j = 0; j < m->status_list._length; j++)
        if (memcmp(m->status_list._buffer[j].goal_info.goal_id.uuid, g.goal_id.uuid, 16) == 0 &&
            m->status_list._buffer[j].status != last_status) {
          last_status = m->status_list._buffer[j].status;
          printf("STATUS %d\n", last_status);
        }
    }
    if (k > 0) dds_return_loan(status, s, k);
    if (cancel_after > 0 && !canceled && feedbacks >= cancel_after) {
      action_msgs_srv_dds__CancelGoal_Request_ c;
      memset(&c, 0, sizeof c);
      memcpy(c.goal_info.goal_id.uuid, g.goal_id.uuid, 16);
      c.request_header.guid = cancel.guid;
      c.request_header.seq = ++cancel.seq;
      dds_write(cancel.req, &c);
      canceled = 1;
    }
    if (canceled == 1 && (rep = take_reply(&cancel, cancel.seq, &loan))) {
      action_msgs_srv_dds__CancelGoal_Response_ *cr = rep;
      printf("CANCEL_RESPONSE %d %u\n", cr->return_code, cr->goals_canceling._length);
      dds_return_loan(cancel.rep, &loan, 1);
      canceled = 2;
    }
    if ((rep = take_reply(&result, result.seq, &loan))) {
      control_msgs_action_dds__FollowJointTrajectory_GetResult_Response_ *rr = rep;
      printf("RESULT %d %d %s\n", rr->status, rr->result.error_code, rr->result.error_string);
      fflush(stdout);
      dds_return_loan(result.rep, &loan, 1);
      return 0;
    }
    fflush(stdout);
    dds_sleepfor(DDS_MSECS(2));
  }
  printf("TIMEOUT\n");
  return 1;
}

/* std_srvs/Trigger client: prints TRIGGER success message */
static int trigger(const char *ns, const char *name) {
  client_t c;
  c.req = writer(topic(&std_srvs_srv_dds__Trigger_Request__desc, "rq/", ns, name, "Request"), qos(1, 0, 100));
  c.rep = reader(topic(&std_srvs_srv_dds__Trigger_Response__desc, "rr/", ns, name, "Reply"), qos(1, 0, 100));
  dds_instance_handle_t ih;
  dds_get_instance_handle(c.req, &ih);
  c.guid = ih;
  c.seq = 0;
  if (!wait_matched_pub(c.req, 20.0) || !wait_matched_sub(c.rep, 20.0)) { printf("NOMATCH\n"); return 1; }
  dds_sleepfor(DDS_MSECS(200));
  std_srvs_srv_dds__Trigger_Request_ r;
  memset(&r, 0, sizeof r);
  r.request_header.guid = c.guid;
  r.request_header.seq = ++c.seq;
  dds_write(c.req, &r);
  void *loan = NULL, *rep = NULL;
  dds_time_t end = dds_time() + DDS_SECS(30);
  while (!(rep = take_reply(&c, c.seq, &loan)) && dds_time() < end) dds_sleepfor(DDS_MSECS(2));
  if (!rep) { printf("NOREPLY\n"); return 1; }
  std_srvs_srv_dds__Trigger_Response_ *t = rep;
  printf("TRIGGER %d %s\n", t->success, t->message);
  dds_return_loan(c.rep, &loan, 1);
  return 0;
}

int main(int argc, char **argv) {
  if (argc < 3) { fprintf(stderr, "usage: see the source\n"); return 2; }
  srand((unsigned)dds_time());
  const char *dom = getenv("ROS_DOMAIN_ID");
  pp = dds_create_participant(dom && *dom ? (dds_domainid_t)atoi(dom) : 0, NULL, NULL);
  if (pp < 0) { fprintf(stderr, "participant: %s\n", dds_strretcode(pp)); return 2; }
  int rc = 2;
  if (!strcmp(argv[1], "listen")) rc = listen(argv[2], atof(argv[3]));
  else if (!strcmp(argv[1], "traj")) rc = traj(argv[2], atof(argv[3]), argc - 4, argv + 4);
  else if (!strcmp(argv[1], "trigger")) rc = trigger(argv[2], argv[3]);
  else if (!strcmp(argv[1], "action")) rc = action(argv[2], atof(argv[3]), atoi(argv[4]), argc - 5, argv + 5);
  fflush(stdout);
  dds_delete(pp);
  return rc;
}
