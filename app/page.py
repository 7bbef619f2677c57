"""The service's web page: upload a STEP part, watch the job, download the mesh and the report."""

INDEX_HTML = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>dst-service</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body { font-family: system-ui, sans-serif; max-width: 46em; margin: 2em auto; padding: 0 1em; color: #222; }
label { display: inline-block; min-width: 11em; } input, select { margin: 0.2em 0; }
progress { width: 100%; } .err { color: #b00; } code { background: #f4f4f4; padding: 0 0.2em; }
</style></head><body>
<h1>dst-service</h1>
<p>Slicing-aware meshes of STEP parts: the mesh's vertex rings lie exactly on your slicer's planes,
so every printed layer follows the exact CAD contour. API: <a href="/docs">/docs</a>,
spec: <a href="/openapi.json">/openapi.json</a>.</p>
<form id="f">
<label>STEP file</label> <input type="file" name="file" accept=".step,.stp,.STEP,.STP" required><br>
<label>Layer height (mm)</label> <input name="layer_height" type="number" step="any" value="0.2"><br>
<label>First layer (mm)</label> <input name="first_layer_height" type="number" step="any" placeholder="= layer height"><br>
<label>Mode</label> <select name="mode"><option>middle</option><option>inclusive</option><option>exclusive</option></select><br>
<label>Target slicer</label> <select name="target_slicer"><option value="">any</option><option>cura</option><option>prusa</option></select><br>
<label>Segment length (mm)</label> <input name="segment_length" type="number" step="any" value="0.8"><br>
<label>Chord error (mm)</label> <input name="chord_error" type="number" step="any" value="0.025"><br>
<label title="the orientation the part is printed in: about x, then y, then z">Turn (degrees)</label>
x <input name="rotate_x" type="number" step="any" value="0" size="5" style="width:5em">
y <input name="rotate_y" type="number" step="any" value="0" size="5" style="width:5em">
z <input name="rotate_z" type="number" step="any" value="0" size="5" style="width:5em"><br>
<label>Report baselines</label> <input name="baselines" value="occt_fast,occt_high_quality,prusaslicer" size="40"><br>
<button>Slice</button>
</form>
<p id="status"></p><progress id="bar" max="1" value="0" hidden></progress>
<p id="links"></p>
<script>
const f = document.getElementById('f'), st = document.getElementById('status'),
      bar = document.getElementById('bar'), links = document.getElementById('links');
f.onsubmit = async (e) => {
  e.preventDefault(); links.textContent = '';
  const data = new FormData(f);
  for (const [k, v] of [...data.entries()]) if (v === '') data.delete(k);
  st.className = ''; st.textContent = 'uploading…';
  const r = await fetch('/v1/jobs', {method: 'POST', body: data});
  const body = await r.json();
  if (!r.ok) { st.className = 'err'; st.textContent = body.error.code + ': ' + body.error.message; return; }
  bar.hidden = false;
  const es = new EventSource(body.links.events);
  const show = (job) => {
    bar.value = job.progress; st.textContent = job.status + ': ' + job.stage;
    if (job.status === 'succeeded') {
      const l = job.links, failed = job.result && job.result.report_error;
      links.innerHTML = '<a href="' + l.mesh + '">mesh (STL)</a> · <a href="' + l.mesh +
        '?format=3mf">mesh (3MF)</a>' + (l.report ? ' · <a href="' + l.report_html +
        '">report</a> · <a href="' + l.report + '">report JSON</a> · <a href="' + l.plot_svg + '">plot</a>' : '');
      if (failed) { st.className = 'err'; st.textContent = 'mesh ready; no deviation report (' + failed.code + '): ' + failed.message; }
    } else if (job.error) { st.className = 'err'; st.textContent = job.error.code + ': ' + job.error.message; }
  };
  es.addEventListener('progress', (m) => show(JSON.parse(m.data)));
  es.addEventListener('end', (m) => { show(JSON.parse(m.data)); es.close(); });
};
</script>
</body></html>
"""
