"""The browser viewer of `ssg view` (docs/view.md): `ssgc.view.page.write_view`."""
