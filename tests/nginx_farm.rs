//! A farm behind nginx, configured by `deploy/nginx/splatd.conf`: three real `splatd serve` nodes,
//! and a real nginx routing by frame id. Every request about a frame lands on one node, and
//! every image equals a single server's.
//!
//! nginx is installed by `tests/setup/nginx.sh` when missing. `SPLATD_SKIP_NGINX=1` skips the
//! test (for machines where it cannot be installed); otherwise a missing nginx is a failure.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::common;
use crate::common::{runtime, Server, ServerProcess};
use splatd_proto::api::{CreateFrame, ImageQuery};
use splatd_proto::{Batch, Client, Record};
use splatd_scenes::synth::FireflyScene;

const FRAMES: u32 = 6;
const PASSES: u64 = 12;

/// nginx in the foreground with everything under one temporary prefix; killed when dropped.
struct Nginx {
    child: Child,
    url: String,
}

impl Drop for Nginx {
    /// SIGTERM first: the master then stops its workers. A SIGKILLed master would leave them
    /// running (and holding the test's output pipes open).
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Runs the setup script and returns the nginx binary, or `None` when the test is skipped.
fn nginx_binary() -> Option<PathBuf> {
    if std::env::var("SPLATD_SKIP_NGINX").as_deref() == Ok("1") {
        eprintln!("SPLATD_SKIP_NGINX=1: skipping the nginx farm test");
        return None;
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/setup/nginx.sh");
    let out = Command::new("bash")
        .arg(&script)
        .stderr(Stdio::inherit())
        .output()
        .expect("running tests/setup/nginx.sh");
    assert!(
        out.status.success(),
        "tests/setup/nginx.sh could not provide nginx (set SPLATD_SKIP_NGINX=1 to skip this test)"
    );
    let path = String::from_utf8(out.stdout).expect("a path");
    let path = path
        .lines()
        .last()
        .expect("the script prints the nginx path")
        .trim();
    Some(PathBuf::from(path))
}

/// The deploy template with the three node addresses and the listen address filled in.
fn render_site(nodes: &[&str], port: u16) -> String {
    let template = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/nginx/splatd.conf"),
    )
    .expect("reading deploy/nginx/splatd.conf");
    let mut site = template.replace("listen 7878;", &format!("listen 127.0.0.1:{port};"));
    assert_ne!(site, template, "the template's `listen 7878;` line is gone");
    for (i, node) in nodes.iter().enumerate() {
        let placeholder = format!("splatd-node-{}:7878", i + 1);
        assert!(
            site.contains(&placeholder),
            "the template lacks {placeholder}"
        );
        site = site.replace(&placeholder, node);
    }
    site
}

/// Starts nginx on a free port; a port that another process took between the probe and nginx's
/// bind makes nginx exit at start, and another port is tried.
fn start_nginx(bin: &Path, dir: &Path, nodes: &[&str]) -> Nginx {
    for _ in 0..5 {
        if let Some(nginx) = try_start_nginx(bin, dir, nodes, common::free_port()) {
            return nginx;
        }
    }
    panic!("nginx exited at start five times; see its messages above");
}

fn try_start_nginx(bin: &Path, dir: &Path, nodes: &[&str], port: u16) -> Option<Nginx> {
    std::fs::write(dir.join("splatd.conf"), render_site(nodes, port)).unwrap();
    // Debian's nginx may be built without some modules; only set the temp paths it knows.
    let version = Command::new(bin).arg("-V").output().unwrap();
    let features = String::from_utf8_lossy(&version.stderr).into_owned();
    let mut temp_paths = String::new();
    for (module, directive) in [
        ("", "client_body_temp_path"),
        ("http_proxy", "proxy_temp_path"),
        ("http_fastcgi", "fastcgi_temp_path"),
        ("http_uwsgi", "uwsgi_temp_path"),
        ("http_scgi", "scgi_temp_path"),
    ] {
        if module.is_empty() || !features.contains(&format!("--without-{module}_module")) {
            let d = dir.join(directive);
            temp_paths.push_str(&format!("    {directive} {};\n", d.display()));
        }
    }
    let conf = format!(
        "worker_processes 1;\nevents {{ worker_connections 512; }}\nhttp {{\n    access_log {};\n{temp_paths}    include {};\n}}\n",
        dir.join("access.log").display(),
        dir.join("splatd.conf").display(),
    );
    let conf_path = dir.join("nginx.conf");
    std::fs::write(&conf_path, conf).unwrap();
    let globals = format!(
        "daemon off; pid {}; error_log stderr;",
        dir.join("nginx.pid").display()
    );
    let child = Command::new(bin)
        .arg("-p")
        .arg(dir)
        .arg("-e")
        .arg("stderr")
        .arg("-c")
        .arg(&conf_path)
        .args(["-g", &globals])
        .stdin(Stdio::null())
        .stdout(Stdio::inherit())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("starting nginx");
    let mut nginx = Nginx {
        child,
        url: format!("http://127.0.0.1:{port}"),
    };
    let deadline = Instant::now() + common::PATIENCE;
    loop {
        if let Ok(Some(status)) = nginx.child.try_wait() {
            eprintln!("nginx exited at start ({status})");
            return None;
        }
        if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
            return Some(nginx);
        }
        assert!(Instant::now() < deadline, "nginx did not listen in time");
        std::thread::sleep(Duration::from_millis(50));
    }
}

struct TestFrame {
    create: CreateFrame,
    scene: FireflyScene,
}

fn test_frames() -> Vec<TestFrame> {
    (0..FRAMES)
        .map(|i| TestFrame {
            create: CreateFrame::new(format!("farm.shot{i:02}"), 20 + 3 * i, 14 + i),
            scene: FireflyScene::new(20 + 3 * i, 14 + i, 700 + i as u64),
        })
        .collect()
}

fn pass_records(scene: &FireflyScene, pass: u64) -> Vec<Record> {
    scene
        .pass(pass)
        .map(|(x, y, rgb)| Record::new(x, y, rgb))
        .collect()
}

/// Creates every frame, then posts every pass of every frame from one task per frame.
/// `header_create`: every other frame is created with a raw request that names the frame only in
/// its JSON body (nginx routes it by the body); the rest go through the Rust client, which also
/// sends `X-Splatd-Frame`.
async fn drive(base: &str, frames: &[TestFrame], header_create: bool) {
    let client = Client::new(base).unwrap();
    let http = reqwest::Client::new();
    for (i, f) in frames.iter().enumerate() {
        if header_create && i % 2 == 1 {
            let r = http
                .post(format!("{base}/v1/frames"))
                .header("content-type", "application/json")
                .body(serde_json::to_vec(&f.create).unwrap())
                .send()
                .await
                .unwrap();
            assert_eq!(r.status().as_u16(), 201, "{}", r.text().await.unwrap());
        } else {
            client.create_frame(&f.create).await.unwrap();
        }
    }
    let mut tasks = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        let client = client.clone();
        let (id, scene) = (f.create.id.clone(), f.scene);
        tasks.push(tokio::spawn(async move {
            for pass in 0..PASSES {
                let records = pass_records(&scene, pass);
                for (k, chunk) in records.chunks(101).enumerate() {
                    let seq = pass * 1000 + k as u64;
                    let batch = Batch::new(id.clone(), 50 + i as u64, seq, chunk.to_vec()).unwrap();
                    client.post_batch(&batch).await.unwrap();
                }
            }
        }));
    }
    for t in tasks {
        t.await.unwrap();
    }
}

/// Create, post and resolve of six frames through nginx: each frame exists on exactly one node,
/// holds every sample there, and its image is byte-identical to a single server's.
#[test]
fn frames_route_by_id_to_one_node_and_resolve_exactly() {
    let Some(bin) = nginx_binary() else {
        return;
    };
    let nodes: Vec<ServerProcess> = (0..3).map(|_| Server::start(&[])).collect();
    let single = Server::start(&[]);
    let dir = tempfile::tempdir().unwrap();
    let addrs: Vec<&str> = nodes.iter().map(|n| n.addr.as_str()).collect();
    let nginx = start_nginx(&bin, dir.path(), &addrs);
    let frames = test_frames();
    let rt = runtime();

    rt.block_on(drive(&nginx.url, &frames, true));
    rt.block_on(drive(&single.url, &frames, false));

    let via_nginx = Client::new(&nginx.url).unwrap();
    let reference = Client::new(&single.url).unwrap();
    let node_clients: Vec<Client> = nodes.iter().map(|n| Client::new(&n.url).unwrap()).collect();
    let mut placement: BTreeMap<String, Vec<usize>> = BTreeMap::new();
    rt.block_on(async {
        for (i, c) in node_clients.iter().enumerate() {
            for info in c.list_frames().await.unwrap() {
                placement.entry(info.id.clone()).or_default().push(i);
            }
        }
    });
    eprintln!("placement of frames on nodes: {placement:?}");
    for f in &frames {
        let on = placement.get(&f.create.id).cloned().unwrap_or_default();
        assert_eq!(
            on.len(),
            1,
            "frame {} is on nodes {on:?}; it must be on exactly one",
            f.create.id
        );
        let pixels = (f.create.width * f.create.height) as u64;
        rt.block_on(async {
            let info = node_clients[on[0]].frame_info(&f.create.id).await.unwrap();
            assert_eq!(
                info.samples,
                PASSES * pixels,
                "frame {}: samples went elsewhere",
                f.create.id
            );
            let query = ImageQuery {
                cascades: true,
                ..ImageQuery::default()
            };
            let got = via_nginx.image(&f.create.id, &query).await.unwrap();
            let expected = reference.image(&f.create.id, &query).await.unwrap();
            assert!(
                got == expected,
                "frame {}: the image through nginx differs from the single server's",
                f.create.id
            );
            // Large bodies stream through in both directions: a state export and re-import.
            let state = via_nginx.export_state(&f.create.id).await.unwrap();
            assert_eq!(
                state,
                reference.export_state(&f.create.id).await.unwrap(),
                "frame {}: state through nginx differs",
                f.create.id
            );
        });
    }
    let total: usize = placement.values().map(Vec::len).sum();
    assert_eq!(total, FRAMES as usize, "unexpected frames on the nodes");
    drop(nginx);
}
