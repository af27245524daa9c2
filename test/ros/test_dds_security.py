"""DDS security of the mapper (docs/security.md): the SROS2 policies shipped in config/security are
in SROS2's format and grant the running node exactly the endpoints its ROS graph shows, and
ROS 2 from the PyPI wheels cannot enforce them, since its Fast DDS is built without the DDS
Security plugins (shown by a real attempt with a valid keystore, not by a version string)."""

import os
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest
from ros_helpers import REPO, NodeLog, Probe, domain_id, ros_env, selected_tests, start

from convbki_ros.params import PARAMETERS

POLICIES = REPO / "config" / "security"
MAPPER_POLICY = POLICIES / "convbki_mapper.policy.xml"
MONITOR_POLICY = POLICIES / "convbki_monitor.policy.xml"
OPERATOR_POLICY = POLICIES / "convbki_operator.policy.xml"
NODE = ("/", "convbki_mapper")  # namespace, name: the node as mapper.launch.py starts it
ENCLAVE = "/convbki_mapper"
WAIT = 30.0  # seconds any one thing may take on a loaded machine before the test gives up

# SROS2's policy format (sros2/policy/schemas/policy.xsd, version 0.2.0): what a profile may
# hold, and the two qualifiers each kind of rule takes.
POLICY_VERSION = "0.2.0"
RULES = {"topics": ("topic", ("publish", "subscribe")), "services": ("service", ("reply", "request")),
         "actions": ("action", ("call", "execute"))}
QUALIFIERS = ("ALLOW", "DENY")
# What every rclpy node holds whatever its job (Node() makes them; /clock with use_sim_time): a
# client's policy may grant these, and its own parameter services, besides what it is for.
NODE_BASICS = {("publish", "/rosout"), ("publish", "/parameter_events"), ("subscribe", "/clock")}
GRAPH_TESTS = {"test_mapper_policy_grants_exactly_the_nodes_endpoints", "test_only_the_operator_may_call_the_node"}
PARAMETER_SERVICES = ("describe_parameters", "get_parameter_types", "get_parameters", "list_parameters",
                      "set_parameters", "set_parameters_atomically", "get_type_description")

# The files rmw_dds_common's get_security_files requires in an enclave's folder (PEM / S/MIME
# forms; a .p11 file may replace a .pem), and what the secure participant would be given.
ENCLAVE_FILES = ("identity_ca.cert.pem", "cert.pem", "key.pem", "permissions_ca.cert.pem", "governance.p7s",
                 "permissions.p7s")
ATTEMPT = ("import rclpy\n"
           "rclpy.init()\n"
           "print('rclpy.init done', flush=True)\n"
           "node = rclpy.create_node('x')\n"
           "print('node created', node.get_fully_qualified_name(), flush=True)\n"
           "node.destroy_node()\n"
           "rclpy.shutdown()\n")


# -- policies ---------------------------------------------------------------------------------------
def resolve(name: str, namespace: str, node: str) -> str:
    """A policy name as SROS2 expands it (its permissions.xsl): "/x" as it is, "~/x" to
    /namespace/node/x, "x" to /namespace/x."""
    if name.startswith("/"):
        return name
    prefix = namespace if namespace.endswith("/") else namespace + "/"
    return prefix + node + name[1:] if name.startswith("~") else prefix + name


def grants(path: Path) -> dict[str, set[tuple[str, str]]]:
    """Per enclave of the policy at ``path``: its ALLOW rules as (direction, resolved name) pairs,
    direction one of publish, subscribe, reply, request, call, execute."""
    result: dict[str, set[tuple[str, str]]] = {}
    for enclave in ElementTree.parse(path).getroot().iter("enclave"):
        allowed = result.setdefault(enclave.get("path"), set())
        for profile in enclave.iter("profile"):
            for rule in profile:
                element, directions = RULES[rule.tag]
                for direction in directions:
                    if rule.get(direction) == "ALLOW":
                        allowed |= {(direction, resolve(item.text.strip(), profile.get("ns"), profile.get("node")))
                                    for item in rule.iter(element)}
    return result


def format_errors(path: Path) -> list[str]:
    """What in the policy at ``path`` breaks SROS2's schema (policy.xsd 0.2.0), as sentences."""
    errors = []
    root = ElementTree.parse(path).getroot()
    if root.tag != "policy" or root.get("version") != POLICY_VERSION:
        errors.append(f"root is <{root.tag} version={root.get('version')!r}>, not <policy version='0.2.0'>")
    if [child.tag for child in root] != ["enclaves"]:
        errors.append(f"<policy> holds {[child.tag for child in root]}, not one <enclaves>")
    for enclaves in root:
        for enclave in enclaves:
            if enclave.tag != "enclave" or not (enclave.get("path") or "").startswith("/"):
                errors.append(f"<{enclave.tag} path={enclave.get('path')!r}> in <enclaves>")
            if not len(enclave) or any(child.tag != "profiles" for child in enclave):
                errors.append(f"enclave {enclave.get('path')} holds {[c.tag for c in enclave]}, not <profiles>")
            for profile in (p for profiles in enclave for p in profiles):
                if profile.tag != "profile" or profile.get("ns") is None or profile.get("node") is None:
                    errors.append(f"<{profile.tag} {profile.attrib}> needs to be a <profile> with ns and node")
                    continue
                for rule in profile:
                    if rule.tag not in RULES:
                        errors.append(f"<{rule.tag}> in a profile (topics, services or actions only)")
                        continue
                    element, directions = RULES[rule.tag]
                    if not rule.attrib or set(rule.attrib) - set(directions) or \
                            set(rule.attrib.values()) - set(QUALIFIERS):
                        errors.append(f"<{rule.tag} {rule.attrib}>: qualifiers are {directions}, ALLOW or DENY")
                    if not len(rule) or any(item.tag != element or not (item.text or "").strip() for item in rule):
                        errors.append(f"<{rule.tag}> must hold non-empty <{element}> elements only")
    return errors


@pytest.mark.parametrize("policy", [MAPPER_POLICY, MONITOR_POLICY, OPERATOR_POLICY], ids=lambda path: path.stem)
def test_policies_are_in_sros2_format(policy):
    """Each shipped policy is what `ros2 security create_permission` reads: a <policy
    version="0.2.0"> of enclaves, profiles with ns and node, and topic / service rules with
    ALLOW qualifiers for their own directions, names without wildcards (every grant is named)."""
    assert format_errors(policy) == []
    (enclave, allowed), = grants(policy).items()
    assert enclave == "/" + policy.name.removesuffix(".policy.xml")
    assert allowed and not [name for _, name in allowed if set(name) & set("*?[]")]
    assert "DENY" not in policy.read_text()  # default is DENY: every rule is an ALLOW


def test_docs_list_every_run_time_parameter():
    """docs/security.md's table of what a caller of set_parameters can change names every
    parameter the node lets change at run time (params.py: run_time=True), and no other."""
    text = (REPO / "docs" / "security.md").read_text()
    section = text.split("Parameters that change at run time", 1)[1].split("\n## ", 1)[0]
    listed = set(re.findall(r"`([a-z_]+)`", section))
    run_time = {spec.name for spec in PARAMETERS if spec.run_time}
    read_only = {spec.name for spec in PARAMETERS if not spec.run_time}
    assert run_time - listed == set()
    assert listed & read_only == set()


# -- DDS Security with the wheels ---------------------------------------------------------------------
def real_ros_install() -> str | None:
    """Why this is not ROS 2 from the PyPI wheels (a real install's Fast DDS may have security)."""
    if os.environ.get("ROS_DISTRO"):
        return f"ROS_DISTRO is set ({os.environ['ROS_DISTRO']}): a ROS 2 install is in use"
    if Path("/opt/ros/jazzy").exists():
        return "/opt/ros/jazzy exists: a ROS 2 install is in use"
    middleware = os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    if not middleware.startswith("rmw_fastrtps"):
        return f"RMW_IMPLEMENTATION is {middleware}, not Fast DDS"
    return None


def openssl(*arguments: str, cwd: Path) -> None:
    result = subprocess.run(["openssl", *arguments], cwd=cwd, capture_output=True, text=True)
    assert result.returncode == 0, f"openssl {' '.join(arguments)}:\n{result.stdout}{result.stderr}"


def access_control_xml(domain: int) -> dict[str, str]:
    """A governance document like SROS2's default one (authenticated participants only, every
    topic encrypted and access-controlled), and permissions that let the enclave publish and
    subscribe every topic of ``domain``."""
    governance = f"""<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance"
    xsi:noNamespaceSchemaLocation="http://www.omg.org/spec/DDS-SECURITY/20170901/omg_shared_ca_governance.xsd">
  <domain_access_rules>
    <domain_rule>
      <domains><id>{domain}</id></domains>
      <allow_unauthenticated_participants>false</allow_unauthenticated_participants>
      <enable_join_access_control>true</enable_join_access_control>
      <discovery_protection_kind>ENCRYPT</discovery_protection_kind>
      <liveliness_protection_kind>ENCRYPT</liveliness_protection_kind>
      <rtps_protection_kind>SIGN</rtps_protection_kind>
      <topic_access_rules>
        <topic_rule>
          <topic_expression>*</topic_expression>
          <enable_discovery_protection>true</enable_discovery_protection>
          <enable_liveliness_protection>true</enable_liveliness_protection>
          <enable_read_access_control>true</enable_read_access_control>
          <enable_write_access_control>true</enable_write_access_control>
          <metadata_protection_kind>ENCRYPT</metadata_protection_kind>
          <data_protection_kind>ENCRYPT</data_protection_kind>
        </topic_rule>
      </topic_access_rules>
    </domain_rule>
  </domain_access_rules>
</dds>
"""
    permissions = f"""<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance"
    xsi:noNamespaceSchemaLocation="http://www.omg.org/spec/DDS-SECURITY/20170901/omg_shared_ca_permissions.xsd">
  <permissions>
    <grant name="{ENCLAVE}">
      <subject_name>CN={ENCLAVE}</subject_name>
      <validity><not_before>2020-01-01T00:00:00</not_before><not_after>2100-01-01T00:00:00</not_after></validity>
      <allow_rule>
        <domains><id>{domain}</id></domains>
        <publish><topics><topic>*</topic></topics></publish>
        <subscribe><topics><topic>*</topic></topics></subscribe>
      </allow_rule>
      <default>DENY</default>
    </grant>
  </permissions>
</dds>
"""
    return {"governance": governance, "permissions": permissions}


def make_keystore(root: Path, domain: int) -> Path:
    """An SROS2-layout keystore made with openssl: one CA (prime256v1, as DDS Security's
    builtin PKI-DH wants) for identities and permissions, and the enclave folder
    root/enclaves/convbki_mapper with the six files rmw looks for, its certificate's subject
    CN=/convbki_mapper, governance and permissions S/MIME-signed by the CA. Checked with
    openssl verify: a failure later is not a broken keystore's."""
    private = root / "private"
    enclave = root / "enclaves" / ENCLAVE.lstrip("/")
    private.mkdir(parents=True)
    enclave.mkdir(parents=True)
    curve = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes")
    openssl("req", "-x509", *curve, "-keyout", "private/ca.key.pem", "-out", "ca.cert.pem", "-days", "2",
            "-subj", "/CN=convbki test CA", cwd=root)
    openssl("req", *curve, "-keyout", str(enclave / "key.pem"), "-out", "private/enclave.csr",
            "-subj", "/CN=\\" + ENCLAVE, cwd=root)  # "\/": a slash in the value, not a separator
    openssl("x509", "-req", "-in", "private/enclave.csr", "-CA", "ca.cert.pem", "-CAkey", "private/ca.key.pem",
            "-set_serial", "2", "-days", "2", "-out", str(enclave / "cert.pem"), cwd=root)
    for name in ("identity_ca.cert.pem", "permissions_ca.cert.pem"):
        shutil.copy(root / "ca.cert.pem", enclave / name)
    for name, text in access_control_xml(domain).items():
        (private / f"{name}.xml").write_text(text)
        openssl("smime", "-sign", "-text", "-in", f"private/{name}.xml", "-out", str(enclave / f"{name}.p7s"),
                "-signer", "ca.cert.pem", "-inkey", "private/ca.key.pem", cwd=root)
        openssl("smime", "-verify", "-in", str(enclave / f"{name}.p7s"), "-CAfile", "ca.cert.pem", "-out",
                os.devnull, cwd=root)
    openssl("verify", "-CAfile", "ca.cert.pem", str(enclave / "cert.pem"), cwd=root)
    assert sorted(path.name for path in enclave.iterdir()) == sorted(ENCLAVE_FILES)
    return enclave


def test_wheels_fast_dds_has_no_security_plugins(tmp_path):
    """With a valid keystore and ROS_SECURITY_ENABLE=true, rcl finds the enclave's folder and
    hands it to rmw_fastrtps, whose Fast DDS (the PyPI wheels') was built without DDS Security:
    creating the node's participant fails, under Enforce and under Permissive alike (a found
    keystore is never ignored). The same environment without ROS_SECURITY_ENABLE starts the
    node: the failure is security's, not the keystore's, the domain's or the attempt's.
    If the node were created securely, the wheels would have security: docs/security.md's
    section on them would be wrong."""
    why = real_ros_install()
    if why:
        pytest.skip(f"{why}; this test is about the PyPI wheels' Fast DDS")
    if not shutil.which("openssl"):
        pytest.skip("openssl is not installed: cannot make a keystore")
    domain = domain_id()
    keystore = tmp_path / "keystore"
    enclave = make_keystore(keystore, domain)
    security = {"ROS_SECURITY_KEYSTORE": str(keystore), "ROS_SECURITY_ENCLAVE_OVERRIDE": ENCLAVE}
    cases = {"enforce": {**security, "ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce"},
             "permissive": {**security, "ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Permissive"},
             "disabled": {**security, "ROS_SECURITY_STRATEGY": "Enforce"}}
    processes = {}
    environment = {key: value for key, value in ros_env(domain).items() if key != "ROS_SECURITY_ENABLE"}
    for case, variables in cases.items():  # at once: each is an rclpy start of its own
        processes[case] = subprocess.Popen([sys.executable, "-c", ATTEMPT], env={**environment, **variables},
                                           cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                           stderr=subprocess.STDOUT, text=True)
    # The mapper itself, told to enforce security there: one line and exit code 2, not a traceback.
    processes["mapper"] = subprocess.Popen([sys.executable, "-m", "convbki_ros.main", "--ros-args", "-p",
                                            "save_on_shutdown:=false"], env={**environment, **cases["enforce"]},
                                           cwd=REPO, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                           stderr=subprocess.PIPE, text=True)
    outputs = {case: process.communicate(timeout=60) for case, process in processes.items()}
    results = {case: (outputs[case][0], process.returncode) for case, process in processes.items()}

    for case in ("enforce", "permissive"):
        output, code = results[case]
        assert code != 0 and "node created" not in output, \
            f"{case}: the node was created with security enabled: the wheels' Fast DDS has security now\n{output}"
        assert "rclpy.init done" in output, output  # the participant is made with the first node
        assert f"Found security directory: {enclave}" in output, output  # rcl found and passed the enclave
        assert "RCLError: error creating node: This Fast DDS version doesn't have the security libraries" in output
        assert "Please compile Fast DDS using the -DSECURITY=ON CMake option" in output, output
        assert "couldn't find all security files" not in output, output

    output, code = results["disabled"]
    assert code == 0 and "node created /x" in output, output
    assert "Found security directory" not in output, output

    _, code = results["mapper"]
    lines = [line for line in outputs["mapper"][1].splitlines() if line.startswith("mapper: ")]
    assert code == 2 and lines == ["mapper: error: ROS 2 could not create the node: error creating node: This Fast DDS "
                                   "version doesn't have the security libraries Please compile Fast DDS using the "
                                   "-DSECURITY=ON CMake option"], (code, lines)


# -- the node's graph against the policy -----------------------------------------------------------
@pytest.fixture(scope="module", autouse=True)
def mapper(request):
    """A mapper node (with use_sim_time, so that it reads /clock) started when the module's first
    test begins, where a test that reads its graph is selected: it boots while the tests before
    those run. (process, its log, its domain), or None."""
    if not GRAPH_TESTS & selected_tests(request):
        yield None
        return
    domain = domain_id()
    process = start("convbki_ros.main", domain, "--ros-args", "-p", "save_on_shutdown:=false",
                    "-p", "use_sim_time:=true", "-p", "device:=cpu")
    log = NodeLog(process)
    try:
        yield process, log, domain
    finally:
        log.close()


@pytest.fixture(scope="module")
def node_graph(mapper):
    """The endpoints of the running mapper as a second process's ROS graph shows them: (direction,
    name) pairs, direction publish, subscribe, reply (a service it serves) or request (a client).
    Waits for "ready", then until the graph holds what the policy grants: endpoints the node has
    beyond those are announced with them."""
    from rclpy.impl.implementation_singleton import rclpy_implementation

    process, log, domain = mapper
    probe = Probe(domain, "security_probe")
    try:
        assert probe.spin_until(lambda: log.find("mapper ready") or process.poll() is not None, 60), \
            log.text()
        assert process.poll() is None, log.text()
        node = probe.node

        def graph() -> set[tuple[str, str]]:
            namespace, name = NODE
            queries = {"publish": node.get_publisher_names_and_types_by_node,
                       "subscribe": node.get_subscriber_names_and_types_by_node,
                       "reply": node.get_service_names_and_types_by_node,
                       "request": node.get_client_names_and_types_by_node}
            try:
                return {(direction, topic) for direction, query in queries.items()
                        for topic, _ in query(name, namespace)}
            except rclpy_implementation.NodeNameNonExistentError:  # ready, but not yet discovered by the probe
                return set()

        expected = grants(MAPPER_POLICY)[ENCLAVE]
        probe.spin_until(lambda: expected <= graph(), WAIT)  # on timeout, the tests name what is missing
        yield graph()
    finally:
        probe.close()


def test_mapper_policy_grants_exactly_the_nodes_endpoints(node_graph):
    """Every topic the running node publishes or subscribes and every service it serves is
    allowed by convbki_mapper.policy.xml in that direction (publish / subscribe; reply for a
    service it answers, request for one it calls), under its resolved name; and the policy
    grants nothing the node does not have: under Enforce the node starts and does its job, and
    its identity is good for nothing else."""
    allowed = grants(MAPPER_POLICY)[ENCLAVE]
    assert sorted(node_graph - allowed) == [], "endpoints of the node that the policy does not allow"
    assert sorted(allowed - node_graph) == [], "grants of the policy that the node has no endpoint for"
    assert {direction for direction, _ in node_graph} == {"publish", "subscribe", "reply"}  # calls nothing


def test_only_the_operator_may_call_the_node(node_graph):
    """The operator's policy requests exactly the node's services (its own, its parameter
    services), and nothing else; the monitor's policy calls no service, publishes none of the
    node's inputs, and reads only what the node publishes (plus /clock); neither policy gives
    its client more than its own node's basics besides."""
    served = {name for direction, name in node_graph if direction == "reply"}
    published = {name for direction, name in node_graph if direction == "publish"}
    inputs = {name for direction, name in node_graph if direction == "subscribe"} - {"/clock"}
    operator = grants(OPERATOR_POLICY)["/convbki_operator"]
    monitor = grants(MONITOR_POLICY)["/convbki_monitor"]
    assert {name for direction, name in operator if direction == "request"} == served
    for client, allowed in (("convbki_operator", operator), ("convbki_monitor", monitor)):
        own_services = {("reply", f"/{client}/{service}") for service in PARAMETER_SERVICES}
        extra = allowed - NODE_BASICS - own_services
        assert {name for direction, name in extra if direction == "publish"} & inputs == set()
        assert {direction for direction, _ in extra} <= {"subscribe", "request"}
        assert {name for direction, name in extra if direction == "subscribe"} <= published
    assert [name for direction, name in monitor if direction == "request"] == []  # the monitor calls nothing
    assert {("subscribe", "/semantic_map"), ("subscribe", "/diagnostics")} <= monitor
