"""colcon's ament_python set-up of coop_viewplan (its package.xml says what it is)."""
from setuptools import find_packages, setup

package_name = 'coop_viewplan'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='Coop Field Robots maintainers',
    maintainer_email='maintainers@coop-field-robots.org',
    description='Information-driven next-best-view and task-directed camera placement '
                '(Sujan 2002, ch. 3.2.4, 3.3.1, ch. 4).',
    license='Apache-2.0',
    entry_points={'console_scripts': [
        'fig_3_13 = coop_viewplan.fig_3_13:main',
        'fig_3_25 = coop_viewplan.fig_3_25:main',
        'table_4_1 = coop_viewplan.table_4_1:main',
        'table_c_1 = coop_viewplan.table_c_1:main',
        'view_planner = coop_viewplan.view_planner_node:main',
    ]},
)
